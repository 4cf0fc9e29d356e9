"""The physics is in the repository: every citation of docs/physics.md names a section
that exists there; every module says what it holds; no docstring or document names a
file that is not in the tree."""

import ast
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PHYSICS = ROOT / "docs" / "physics.md"

# "docs/physics.md section 8.3", "... sections 5-7", "... sections 1 and 3", "... sections 5.1 and 8.2"
CITATION = re.compile(r"(\S*)physics\.md(?:`{1,2})?(?:\s+(sections?)\s+"
                      r"(\d+(?:\.\d+)*(?:\s*(?:-|and)\s*\d+(?:\.\d+)*)*))?")
# files that may point at the document as a whole (no section)
WHOLE_DOCUMENT_OK = {"README.md", "docs/DEVELOPING.md"}


def _tracked(*patterns):
    out = subprocess.run(["git", "ls-files", *patterns], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout.split()
    return [ROOT / p for p in out if (ROOT / p).is_file()]


def _sections():
    heads = re.findall(r"^#{2,4} (\d+(?:\.\d+)*)\.? ", PHYSICS.read_text(), flags=re.M)
    return set(heads)


def _cited(numbers):
    """'5-7' -> 5, 6, 7; '1 and 3' -> 1, 3; '5.1 and 8.2' -> 5.1, 8.2."""
    out = []
    for part in re.split(r"\s*and\s*", numbers):
        if "-" in part:
            lo, hi = part.split("-")
            out += [str(i) for i in range(int(lo), int(hi) + 1)]
        else:
            out.append(part)
    return out


def citations(text):
    """(prefix, section numbers or None) of every mention of physics.md in ``text``."""
    return [(m.group(1), _cited(m.group(3)) if m.group(3) else None)
            for m in CITATION.finditer(text)]


def test_the_document_has_its_sections():
    have = _sections()
    assert {str(i) for i in range(1, 11)} <= have
    assert {"2.2", "3.3", "3.4", "6.1", "8.3"} <= have


def test_the_citation_parser():
    found = citations("see ``docs/physics.md`` section 8.3; (docs/physics.md sections 5-7) "
                      "and ../shared/reference/physics.md")
    assert found == [("``docs/", ["8.3"]), ("(docs/", ["5", "6", "7"]),
                     ("../shared/reference/", None)]


def test_every_citation_resolves_to_a_section():
    sections = _sections()
    problems = []
    count = 0
    for path in _tracked("*.py", "*.md", "*.txt", "*.toml", "*.cfg", "Makefile"):
        rel = path.relative_to(ROOT).as_posix()
        if rel in ("docs/physics.md", "Testing/Python/test_physics_doc.py"):
            continue
        for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            for prefix, numbers in citations(line):
                count += 1
                where = f"{rel}:{lineno}"
                path_part = prefix.lstrip("`'\"(*[")
                if not (path_part.startswith("docs/") or
                        (path_part == "" and rel in WHOLE_DOCUMENT_OK)):
                    problems.append(f"{where}: cites {prefix}physics.md, not docs/physics.md")
                if numbers is None:
                    if rel not in WHOLE_DOCUMENT_OK:
                        problems.append(f"{where}: cites docs/physics.md without a section")
                    continue
                problems += [f"{where}: docs/physics.md has no section {n}"
                             for n in numbers if n not in sections]
    assert count > 40
    assert not problems, "\n".join(problems)


def test_every_module_says_what_it_holds():
    missing = []
    for path in _tracked("*.py"):
        if path.name == "conftest.py" or path.stat().st_size == 0:
            continue
        doc = ast.get_docstring(ast.parse(path.read_text()))
        if not doc or len(doc) < 15:
            missing.append(path.relative_to(ROOT).as_posix())
    assert not missing, "modules without a docstring: " + ", ".join(missing)


@pytest.mark.parametrize("kind", ["*.py", "*.md"])
def test_no_file_names_a_module_that_is_gone(kind):
    """A ``name.py`` in a docstring, comment or document is a file in the tree, and no
    text uses the names the layout of afc0a5a retired (``igft_steps.acquire``)."""
    names = {p.name for p in _tracked("*.py")}
    bad = []
    for path in _tracked(kind):
        rel = path.relative_to(ROOT).as_posix()
        if rel == "Testing/Python/test_physics_doc.py":
            continue
        text = path.read_text(errors="replace")
        bad += [f"{rel}: {m.group(1)}"
                for m in re.finditer(r"(?<![\w/.>-])([A-Za-z_]\w*\.py)\b", text)
                if m.group(1) not in names and m.group(1) != "x.py"]
        bad += [f"{rel}: {m.group(0)}" for m in re.finditer(r"\bigft_\w+", text)]
    assert not bad, "\n".join(sorted(set(bad)))


def test_developing_md_names_every_folder_and_foundation_module():
    """docs/DEVELOPING.md's picture and table stay true: every Lib subpackage, every
    application folder and every foundation module is in it."""
    text = (ROOT / "docs" / "DEVELOPING.md").read_text()
    missing = []
    for lib in ("FluoCalib/FluoCalibLib", "FluoNav/FluoNavLib", "FluoTomo/FluoTomoLib"):
        for init in sorted((ROOT / lib).glob("*/__init__.py")):
            if f"{lib}/{init.parent.name}/" not in text:
                missing.append(f"{lib}/{init.parent.name}/")
    for sub in sorted((ROOT / "fluoapp").glob("*/__init__.py")):
        if f"fluoapp/{sub.parent.name}/" not in text:
            missing.append(f"fluoapp/{sub.parent.name}/")
    for mod in sorted((ROOT / "fluoguide").glob("*.py")):
        if mod.name != "__init__.py" and f"`{mod.name}`" not in text:
            missing.append(f"fluoguide/{mod.name}")
    assert not missing, "docs/DEVELOPING.md does not mention " + ", ".join(missing)
