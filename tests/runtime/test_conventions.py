"""Conventions of the tree that a reader relies on, checked by reading the tree."""
import ast
from pathlib import Path

from common import layout

REPO = Path(__file__).resolve().parents[2]


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


# What each package of common/ may import: the layers of common/layout.py (docs/architecture.md).
LEAVES = set(layout.LEAVES)
MAY_IMPORT = {name: set(deps) for name, deps in layout.MAY_IMPORT.items()}


def _imports(path: Path, root: Path = REPO):
    """(imported module, line) of every import in ``path`` (under ``root``), function-level ones
    too, relative ones resolved."""
    parts = path.relative_to(root).with_suffix("").parts
    package = parts if path.name == "__init__.py" else parts[:-1]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(package[:len(package) - node.level + 1])
                yield base + ("." + node.module if node.module else ""), node.lineno
            else:
                yield node.module, node.lineno


def test_every_package_imports_only_what_the_architecture_allows():
    """The layering of docs/architecture.md: geometry and the runtime stand alone, the library
    never imports ``nodes/`` (a graph's node classes are loaded by module name,
    ``common.runtime.node.node_class``), and each package imports only the packages below it."""
    assert set(MAY_IMPORT) == {p.stem if p.is_file() else p.name for p in (REPO / "common").iterdir()
                               if (p.suffix == ".py" and p.stem != "__init__") or (p / "__init__.py").exists()}
    bad = []
    for path in sorted(REPO.glob("common/**/*.py")):
        rel = path.relative_to(REPO)
        pkg = rel.parts[1] if len(rel.parts) > 2 else rel.stem
        for mod, line in _imports(path):
            top = mod.split(".")
            if top[0] == "nodes":
                bad.append(f"{rel}:{line}: imports {mod} (the library never imports nodes/)")
            elif top[0] == "common" and len(top) > 1 and top[1] != pkg:
                if top[1] not in LEAVES and top[1] not in MAY_IMPORT[pkg]:
                    bad.append(f"{rel}:{line}: {pkg} imports {mod}")
    assert not bad, "\n".join(bad)


def test_the_layering_check_sees_what_it_guards(tmp_path):
    """The import scan finds top-level, function-level and relative imports."""
    p = tmp_path / "common" / "runtime" / "x.py"
    p.parent.mkdir(parents=True)
    p.write_text("import common.geometry\ndef f():\n    from nodes.detector import D\n"
                 "from .graph import load_graph\nfrom ..sim import render\n")
    found = sorted(_imports(p, tmp_path), key=lambda x: x[1])
    assert found == [("common.geometry", 1), ("nodes.detector", 3), ("common.runtime.graph", 4),
                     ("common.sim", 5)], found


def test_the_package_docs_are_written_from_the_code():
    """Each package's ``__init__`` docstring lists its modules and docs/architecture.md's package
    table lists every package and module, as ``python -m common.layout`` writes them."""
    stale = [f"common/{p}/__init__.py" for p in layout.packages()
             if ast.get_docstring(ast.parse((REPO / "common" / p / "__init__.py").read_text()))
             != layout.init_docstring(p).strip()]
    page = (REPO / "docs" / "architecture.md").read_text()
    if layout.architecture_page(page) != page:
        stale.append("docs/architecture.md")
    assert not stale, f"stale: {stale}: run python -m common.layout"


def test_a_module_summary_is_its_docstrings_first_sentence():
    assert layout.summary("Poses, e.g. T_a_b, in metres. More.\n\nDetails.") == "Poses, e.g. T_a_b, in metres."
    assert layout.summary("A usage line\nwithout a stop\n\nthen more.") == "A usage line without a stop"
    assert layout.summary(None) == ""


def _private_imports(path: Path):
    """(line, name) of every private name (``_x``, not ``__x__``) that ``path`` imports: a name
    from another module (``from m import _x``) or a private module itself (``import a._m``)."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    yield node.lineno, alias.name
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if any(p.startswith("_") and not p.startswith("__") for p in alias.name.split(".")):
                    yield node.lineno, alias.name


def test_no_private_name_is_imported_across_modules():
    """Modules are split where the code separates: a name another module needs is public (no
    ``_x`` imported from another module of ``common/`` or ``nodes/``)."""
    bad = []
    for path in sorted([*REPO.glob("common/**/*.py"), *REPO.glob("nodes/*.py")]):
        rel = str(path.relative_to(REPO))
        bad += [f"{rel}:{line}: imports {name}" for line, name in _private_imports(path)]
    assert not bad, "\n".join(bad)


def test_the_private_import_check_sees_what_it_guards(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("from a.b import _x, y, __version__\nimport a._c\ndef f():\n    from .d import _e\n")
    assert sorted(_private_imports(p)) == [(1, "_x"), (2, "a._c"), (4, "_e")]
