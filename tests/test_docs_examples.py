"""The documentation is executable and in step with the code.

- Every ```python block of README.md and docs/*.md runs, each in a fresh
  namespace and a temporary working folder (examples that write files do not
  litter the repository). A block whose first line is a comment starting with
  ``# not run`` is not an example (it is not collected). A failure names the
  file, the block's line and its first line, and the traceback points at the
  Markdown line that failed.
- docs/api.md: every listed signature names the parameters of the real
  function, in order and of the right kind; listed defaults and constant values
  that are literals (or module constants) equal the code's; every public
  function and class of every public module is listed.
- Relative links between the pages resolve; docs/index.md quotes the headline
  ratios of the current docs/results.md.
- ``import hvo_graph`` stays light, and every lazily re-exported name resolves.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
import re
import subprocess
import sys
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import hvo_graph

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
API = ROOT / "docs" / "api.md"
NOT_RUN = "# not run"

# -- running the examples ----------------------------------------------------------------------


@dataclass(frozen=True)
class Block:
    path: Path
    index: int  # 0-based among the file's python blocks
    line: int  # 1-based line of the first code line
    code: str

    @property
    def name(self) -> str:
        return f"{self.path.relative_to(ROOT)}#{self.index}"

    @property
    def first_line(self) -> str:
        return next((s.strip() for s in self.code.splitlines() if s.strip()), "")


def python_blocks(path: Path) -> list[Block]:
    """The ```python fenced blocks of a Markdown file (fences may be indented)."""
    blocks: list[Block] = []
    lines = path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        opening = lines[i].strip()
        if opening.startswith("```") and opening[3:].strip().lower() in ("python", "py"):
            indent = len(lines[i]) - len(lines[i].lstrip())
            start = i + 1
            end = start
            while end < len(lines) and lines[end].strip() != "```":
                end += 1
            if end == len(lines):
                raise AssertionError(f"{path}:{i + 1}: unclosed ```python block")
            code = "\n".join(line[indent:] for line in lines[start:end]) + "\n"
            blocks.append(Block(path, len(blocks), start + 1, code))
            i = end
        i += 1
    return blocks


ALL_BLOCKS = [b for path in DOC_FILES for b in python_blocks(path)]
EXAMPLES = [b for b in ALL_BLOCKS if not b.first_line.lower().startswith(NOT_RUN)]


def test_the_docs_have_examples():
    files = {b.path.name for b in EXAMPLES}
    assert {"README.md", "api.md"} <= files
    assert len([b for b in EXAMPLES if b.path == API]) >= 8  # the workflows (a) to (h)


@pytest.mark.parametrize("block", EXAMPLES, ids=[b.name for b in EXAMPLES])
def test_example_runs(block: Block, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    # Padding with blank lines makes the traceback's line numbers those of the Markdown file.
    source = "\n" * (block.line - 1) + block.code
    namespace = {"__name__": "__docs_example__"}
    error = None
    try:
        exec(compile(source, str(block.path), "exec"), namespace)
    except Exception:
        error = traceback.format_exc()
    if error is not None:  # outside the except: no "during handling" noise in the report
        pytest.fail(
            f"{block.path.relative_to(ROOT)}:{block.line}: example {block.index} "
            f"({block.first_line!r}) failed:\n{error}",
            pytrace=False,
        )


# -- docs/api.md against the code --------------------------------------------------------------


@dataclass(frozen=True)
class Entry:
    module: str
    qualname: str  # e.g. "estimate_homography", "CameraModel.project"
    params: tuple[str, ...] | None  # None: no parenthesis (constant, attribute, property)
    value: str | None  # "NAME = value" entries
    line: int


_MODULE_HEADING = re.compile(r"^#+ `(hvo_graph(?:\.\w+)+)`")
_ENTRY = re.compile(r"^- `([^`]+)`")


def _split_top_level(text: str) -> list[str]:
    """Split at commas outside brackets and quotes."""
    parts, depth, quote, current = [], 0, "", []
    for ch in text:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append("".join(current).strip())
            current = []
            continue
        current.append(ch)
    if "".join(current).strip():
        parts.append("".join(current).strip())
    return parts


def _parse_entry(module: str, span: str, line: int) -> Entry:
    m = re.match(r"^([A-Za-z_][\w.]*)\s*(.*)$", span)
    assert m, f"{API.name}:{line}: cannot read the entry `{span}`"
    name, rest = m.groups()
    if rest.startswith("("):
        depth = np.cumsum([(ch == "(") - (ch == ")") for ch in rest])
        close = int(np.flatnonzero(depth == 0)[0])  # the parenthesis matching the first
        return Entry(module, name, tuple(_split_top_level(rest[1:close])), None, line)
    value = rest[1:].strip() if rest.startswith("=") else None
    return Entry(module, name, None, value, line)


def api_entries() -> list[Entry]:
    entries: list[Entry] = []
    module: str | None = None
    for n, text in enumerate(API.read_text(encoding="utf-8").splitlines(), start=1):
        if text.startswith("#"):
            heading = _MODULE_HEADING.match(text)
            module = heading.group(1) if heading else None
            continue
        entry = _ENTRY.match(text)
        if module is not None and entry:
            entries.append(_parse_entry(module, entry.group(1), n))
    return entries


ENTRIES = api_entries()


def _resolve(entry: Entry) -> object:
    obj: object = importlib.import_module(entry.module)
    for part in entry.qualname.split("."):
        assert hasattr(obj, part), (
            f"docs/api.md:{entry.line}: {entry.module}.{entry.qualname} does not exist"
        )
        obj = inspect.getattr_static(obj, part) if inspect.isclass(obj) else getattr(obj, part)
    return obj


def _expected_value(text: str, module: object) -> tuple[bool, object]:
    """(known, value) of a documented default or constant: a literal or a module constant."""
    try:
        return True, ast.literal_eval(text)
    except (ValueError, SyntaxError):
        pass
    if re.fullmatch(r"[A-Za-z_]\w*", text) and hasattr(module, text):
        return True, getattr(module, text)
    return False, None


def _same(documented: object, actual: object) -> bool:
    if isinstance(actual, np.ndarray) or (
        isinstance(actual, tuple | list)
        and actual
        and all(isinstance(x, int | float) for x in actual)
    ):
        a, d = np.asarray(actual, dtype=float), np.asarray(documented, dtype=float)
        return a.shape == d.shape and np.allclose(a, d, rtol=1e-12, atol=0.0)
    if isinstance(actual, float) and isinstance(documented, int | float):
        return np.isclose(actual, documented, rtol=1e-12, atol=0.0)
    return documented == actual


def _documented_parameters(entry: Entry, module: object) -> list[tuple[str, str, str | None]]:
    """(name, kind, default text) per documented parameter; kind as in inspect."""
    out, keyword_only = [], False
    assert entry.params is not None
    for item in entry.params:
        if item == "*":
            keyword_only = True
        elif item.startswith("**"):
            out.append((item[2:], "VAR_KEYWORD", None))
        elif item.startswith("*"):
            out.append((item[1:], "VAR_POSITIONAL", None))
            keyword_only = True
        else:
            name, _, default = item.partition("=")
            kind = "KEYWORD_ONLY" if keyword_only else "POSITIONAL_OR_KEYWORD"
            out.append((name.strip(), kind, default.strip() or None))
    return out


@pytest.mark.parametrize(
    "entry", ENTRIES, ids=[f"{e.module.removeprefix('hvo_graph.')}.{e.qualname}" for e in ENTRIES]
)
def test_api_entry_matches_the_code(entry: Entry):
    obj = _resolve(entry)
    module = importlib.import_module(entry.module)
    where = f"docs/api.md:{entry.line}: {entry.qualname}"
    if entry.value is not None:
        known, documented = _expected_value(entry.value, module)
        assert known, f"{where}: the value '{entry.value}' is not a literal"
        assert _same(documented, obj), f"{where}: documented {entry.value}, the code has {obj!r}"
    if entry.params is None:
        return
    if isinstance(obj, staticmethod | classmethod):
        obj = obj.__func__
    assert callable(obj), f"{where}: documented with a signature but not callable"
    params = list(inspect.signature(obj).parameters.values())
    if inspect.isfunction(obj) and "." in entry.qualname and params and params[0].name == "self":
        params = params[1:]
    actual = [(p.name, p.kind.name) for p in params]
    documented = _documented_parameters(entry, module)
    assert [(n, k) for n, k, _ in documented] == actual, (
        f"{where}: documented parameters {[(n, k) for n, k, _ in documented]}, "
        f"the code has {actual}"
    )
    for (name, _, default), p in zip(documented, params, strict=True):
        if default is None:
            continue
        assert p.default is not inspect.Parameter.empty, f"{where}: {name} has no default"
        known, value = _expected_value(default, module)
        if known:
            assert _same(value, p.default), (
                f"{where}: {name}={default} documented, the code's default is {p.default!r}"
            )


def public_modules() -> list[str]:
    names = []
    for info in pkgutil.walk_packages(hvo_graph.__path__, "hvo_graph."):
        parts = info.name.split(".")
        if info.ispkg or any(p.startswith("_") for p in parts):
            continue
        names.append(info.name)
    return sorted(names)


def test_every_public_module_function_and_class_is_in_the_api_reference():
    documented = {(e.module, e.qualname) for e in ENTRIES}
    sections = {e.module for e in ENTRIES}
    missing = []
    for name in public_modules():
        if name not in sections:
            missing.append(f"{name} (no section)")
            continue
        module = importlib.import_module(name)
        for attr, obj in vars(module).items():
            if attr.startswith("_") or getattr(obj, "__module__", None) != name:
                continue
            if (inspect.isfunction(obj) or inspect.isclass(obj)) and (name, attr) not in documented:
                missing.append(f"{name}.{attr}")
    assert not missing, "not in docs/api.md: " + ", ".join(missing)


# -- links and quoted numbers ------------------------------------------------------------------

_LINK = re.compile(r"\]\(([^)\s]+)\)")


def anchors(path: Path) -> set[str]:
    """GitHub's heading anchors of a Markdown page (lower case, punctuation dropped,
    spaces to hyphens; repeated headings get -1, -2, ...)."""
    seen: dict[str, int] = {}
    out = set()
    in_code = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.strip().startswith("```"):
            in_code = not in_code
        heading = re.match(r"^#{1,6} (.*)$", line)
        if in_code or not heading:
            continue
        slug = re.sub(r"[^\w\- ]", "", heading.group(1).strip().lower()).replace(" ", "-")
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        out.add(slug if count == 0 else f"{slug}-{count}")
    return out


@pytest.mark.parametrize("path", DOC_FILES, ids=[str(p.relative_to(ROOT)) for p in DOC_FILES])
def test_relative_links_resolve(path: Path):
    text = path.read_text(encoding="utf-8")
    broken = []
    for target in _LINK.findall(text):
        if re.match(r"^[a-z]+:", target):
            continue  # a web address
        file, _, anchor = target.partition("#")
        linked = path.parent / file if file else path
        if not linked.exists():
            broken.append(target)
        elif anchor and linked.suffix == ".md" and anchor not in anchors(linked):
            broken.append(target)
    assert not broken, f"{path.relative_to(ROOT)}: links to missing files or headings: {broken}"


def test_index_links_every_doc_page():
    index = (ROOT / "docs" / "index.md").read_text(encoding="utf-8")
    linked = {Path(t.split("#")[0]).name for t in _LINK.findall(index)}
    pages = {p.name for p in (ROOT / "docs").glob("*.md")} - {"index.md"}
    assert pages <= linked, f"docs/index.md does not link {sorted(pages - linked)}"


def test_index_quotes_the_current_results():
    """The headline ratios in docs/index.md are those of docs/results.md (within rounding)."""
    results = (ROOT / "docs" / "results.md").read_text(encoding="utf-8")
    seeds = re.search(r"\((\d+) seeds\)", results)
    row = re.search(r"^\| ISAM2 smoothed / Kalman \(paper, noisy R\)\s*\|(.*)\|$", results, re.M)
    assert seeds and row, "docs/results.md: seed count or the smoothed / paper-Kalman row missing"
    measured = [float(cell.split("±")[0]) for cell in row.group(1).split("|")]
    index = (ROOT / "docs" / "index.md").read_text(encoding="utf-8")
    quoted = re.search(
        r"on (\d+) seeds.*?position ([\d.]+), orientation ([\d.]+), "
        r"linear velocity ([\d.]+) and angular velocity ([\d.]+)",
        " ".join(index.split()),
    )
    assert quoted, "docs/index.md: the sentence quoting the ratios was not found"
    assert quoted.group(1) == seeds.group(1)
    assert np.allclose([float(x) for x in quoted.groups()[1:]], measured, rtol=0.02, atol=0.0)


# -- the package namespace ---------------------------------------------------------------------


def test_import_hvo_graph_is_light():
    code = (
        "import sys, hvo_graph, hvo_graph.geometry, hvo_graph.estimators, hvo_graph.io; "
        "print(' '.join(m for m in ('gtsam', 'cv2', 'matplotlib', 'yaml') if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == ""


@pytest.mark.parametrize("package", ["hvo_graph", "geometry", "estimators", "io"])
def test_lazy_exports_resolve_to_the_defining_objects(package: str):
    name = package if package == "hvo_graph" else f"hvo_graph.{package}"
    pkg = importlib.import_module(name)
    for attr in pkg.__all__:
        value = getattr(pkg, attr)
        if attr == "__version__":
            continue
        origin = getattr(value, "__module__", None)
        if origin is not None and origin.startswith("hvo_graph."):
            assert getattr(importlib.import_module(origin), attr) is value
        assert attr in dir(pkg)
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        pkg.not_a_name  # noqa: B018
