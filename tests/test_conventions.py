"""Conventions of the tree that a reader relies on, checked by reading the tree."""
import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_every_error_class_derives_from_the_projects_base():
    """One base for the project's own errors (common/errors.py), found by reading the tree."""
    import importlib
    import inspect

    from common.errors import NeedletrackError
    missing = []
    for path in REPO.glob("common/**/*.py"):
        tree = ast.parse(path.read_text(), str(path))
        names = [n.name for n in tree.body if isinstance(n, ast.ClassDef)
                 and (n.name.endswith("Error") or n.name == "NoPose")]
        if not names:
            continue
        mod = importlib.import_module(".".join(path.relative_to(REPO).with_suffix("").parts))
        for name in names:
            cls = getattr(mod, name)
            if inspect.isclass(cls) and issubclass(cls, Exception) and not issubclass(cls, NeedletrackError):
                missing.append(f"{path.relative_to(REPO)}:{name}")
    assert not missing, missing


def test_the_readme_is_a_front_door_and_every_link_in_the_docs_resolves():
    import re
    readme = REPO / "README.md"
    assert len(readme.read_text().splitlines()) <= 180
    broken = []
    for page in [readme, *REPO.glob("docs/*.md"), REPO / "models" / "README.md"]:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (page.parent / target).exists():
                broken.append(f"{page.relative_to(REPO)}: {target}")
    assert not broken, broken


def test_the_cameras_are_named_in_one_place():
    import re
    found = [f"{p.relative_to(REPO)}:{i + 1}" for p in [*REPO.glob("common/**/*.py"), *REPO.glob("nodes/*.py")]
             for i, line in enumerate(p.read_text().splitlines())
             if re.match(r"^\s*(CAMERAS|CAMS)\s*=", line)]
    assert found == ["common/frames.py:7"], found
