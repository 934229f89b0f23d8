"""The library's layout, declared once: the layer order of ``common/`` (``MAY_IMPORT``: what each
package or top-level module may import), and the module lists written from the code into each
package's ``__init__`` docstring and docs/architecture.md (``python -m common.layout``).

Each module's summary is its docstring's first sentence; a package's role is its ``__init__``
docstring's first paragraph, written by hand. Reads the files (``ast``), imports nothing.
"""
from __future__ import annotations

import ast
import re
import sys
import textwrap
from pathlib import Path

COMMON = Path(__file__).resolve().parent
ARCHITECTURE = COMMON.parent / "docs" / "architecture.md"

LEAVES = ("errors", "frames", "methods", "palette", "progress", "cli_options", "layout", "constraints")
"""Import nothing of ``common`` (``palette`` only ``methods``); anything may import them."""

_BELOW_EVALUATION = ("geometry", "runtime", "data", "sim", "detector", "ros", "pose", "viewer", "label", "cli")
MAY_IMPORT = {
    "errors": (), "frames": (), "methods": (), "palette": ("methods",), "progress": (), "cli_options": (),
    "layout": (), "constraints": (),
    "geometry": (),
    "runtime": (),
    "data": ("geometry", "runtime"),
    "sim": ("geometry", "data"),
    "detector": ("geometry", "data", "runtime"),
    "ros": ("geometry", "data", "runtime"),
    "pose": ("geometry", "data", "runtime"),
    "viewer": ("geometry", "runtime", "data"),
    "label": ("geometry", "runtime", "data", "detector", "viewer"),
    "evaluation": _BELOW_EVALUATION,
    "bench": (*_BELOW_EVALUATION, "evaluation"),
    "robustness": (*_BELOW_EVALUATION, "evaluation", "bench"),
    "adapt": (*_BELOW_EVALUATION, "evaluation", "bench"),
    "cli": ("data",),
}
"""The layers, in order: each package (or top-level module) of ``common/`` and the others it may
import besides the leaves; ``tests/runtime/test_conventions.py`` holds every import to it."""

MODULES_HEAD = "Modules (``python -m common.layout`` writes this list from their docstrings):"
TABLE_BEGIN = "<!-- the package table: python -m common.layout writes it from the code -->"
TABLE_END = "<!-- end of the package table -->"


def summary(doc: str | None) -> str:
    """A docstring's first sentence, on one line (its first paragraph when it has no full stop)."""
    para = " ".join((doc or "").strip().split("\n\n")[0].split())
    m = re.search(r"(?<!e\.g)(?<!i\.e)(?<!\bvs)(?<!\bcf)[.!?](\s|$)", para)
    return para[:m.start() + 1] if m else para


def _doc(path: Path) -> str | None:
    return ast.get_docstring(ast.parse(path.read_text(), str(path)))


def modules(package: str) -> list[tuple[str, str]]:
    """(module name, summary) of each module of ``common/<package>/``, by name."""
    return [(p.stem, summary(_doc(p))) for p in sorted((COMMON / package).glob("*.py")) if p.stem != "__init__"]


def role(name: str) -> str:
    """A package's role (its ``__init__`` docstring's hand-written first paragraph) or a
    top-level module's summary."""
    path = COMMON / name / "__init__.py" if (COMMON / name).is_dir() else COMMON / f"{name}.py"
    doc = _doc(path) or ""
    return " ".join(doc.split("\n\n")[0].split()) if path.name == "__init__.py" else summary(doc)


def init_docstring(package: str) -> str:
    """What ``common/<package>/__init__.py``'s docstring should be: its hand-written part (all
    before ``MODULES_HEAD``), then the list of its modules."""
    doc = _doc(COMMON / package / "__init__.py") or ""
    lead = doc.split(MODULES_HEAD)[0].rstrip()
    items = "\n".join(textwrap.fill(f"- ``{name}``: {text}", width=100, subsequent_indent="  ",
                                     break_long_words=False, break_on_hyphens=False)
                       for name, text in modules(package))
    return f"{lead}\n\n{MODULES_HEAD}\n\n{items}\n"


def _md(text: str) -> str:
    return text.replace("``", "`").replace("|", "\\|")


def table() -> str:
    """docs/architecture.md's package table, in layer order, with each package's modules."""
    rows = [TABLE_BEGIN, "", "| package | what it holds | may import |", "| --- | --- | --- |"]
    for name, deps in MAY_IMPORT.items():
        is_pkg = (COMMON / name).is_dir()
        what = _md(role(name))
        if is_pkg:
            what += "<br>" + ", ".join(f"`{m}`" for m, _ in modules(name))
        may = ", ".join(f"`{d}`" for d in deps) or "nothing else of `common`"
        rows.append(f"| `common/{name}{'/' if is_pkg else '.py'}` | {what} | {may} |")
    rows += ["", "Each package's modules, with their docstrings' first sentences:", ""]
    for name in packages():
        rows.append(f"- `common/{name}/`")
        rows += [f"  - `{m}`: {_md(t)}" for m, t in modules(name)]
    return "\n".join(rows + ["", TABLE_END])


def architecture_page(text: str) -> str:
    """``text`` (docs/architecture.md) with its package table as ``table()`` gives it."""
    begin, end = text.index(TABLE_BEGIN), text.index(TABLE_END) + len(TABLE_END)
    return text[:begin] + table() + text[end:]


def packages() -> list[str]:
    return [n for n in MAY_IMPORT if (COMMON / n).is_dir()]


def _write_init(package: str) -> None:
    path = COMMON / package / "__init__.py"
    src = path.read_text()
    node = ast.parse(src).body[0]
    lines = src.splitlines(True)
    new = '"""' + init_docstring(package) + '"""\n'
    path.write_text("".join(lines[:node.lineno - 1]) + new + "".join(lines[node.end_lineno:]))
    if _doc(path) != init_docstring(package).strip():
        raise SystemExit(f"{path}: a module's summary does not survive in a docstring (a backslash?)")


def main(argv=None) -> int:
    """``python -m common.layout``: rewrite the packages' ``__init__`` docstrings and
    docs/architecture.md's package table from the code."""
    for package in packages():
        _write_init(package)
    ARCHITECTURE.write_text(architecture_page(ARCHITECTURE.read_text()))
    print(f"wrote {len(packages())} package docstrings and {ARCHITECTURE}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
