"""No hand-typed measurement in what a reader reads (issue 39): every number in the
notebooks' prose, the chapter backends' strings and the README is glued from the run, or a
definition (the paper's settings, the data format, the method's constants: DEFINED, each
with its reason), or restates the code beside it (a Try-it command's ``--set``), or, in the
README, sits in a block that cites the dated record it comes from (``benchmarks/*.md``).
Seconds: text only."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"))
BACKENDS = sorted((ROOT / "src" / "flowmod" / "chapters").glob("*.py"))

#: Numbers that are definitions, not measurements: (pattern, why it may be typed).
DEFINED: tuple[tuple[str, str], ...] = (
    (r"\b30-70 m\b|(?:<|than|from|at) 30 m\b|\(30 m\)", "the paper's distance band (Table 1)"),
    (r"\b2 m/s\b|\bbetween 2 and\b|\b2 Hz\b|\b12 Hz\b|\b0\.5 s\b|\b1600 x 90[04]\b|"
     r"\b13 tables\b|\bkeyframes: 6\b|\babout 34 000\b",
     "nuScenes and the paper's label: keyframes at 2 Hz, sweeps at 12 Hz, 2 m/s"),
    (r"\b224 x 224\b|\b224 px\b|\b60 epochs\b|\bbatch(?:es)? of 128\b|\b1 of 2\b",
     "the paper's Table 2 and the original code's protocol"),
    (r"\b4 camera frames\b", "the paper's generalisation pairs (Table 4)"),
    (r"\b95 ?%|\bexcludes 0\b|\bcontains 0\b", "the intervals' level and the null effect"),
    (r"\b(?:exceeds|probability|at) 0\.5\b", "the decision threshold, the flip probability"),
    (r"\b3 px and 5 %", "KITTI's Fl-all outlier definition"),
    (r"\b[0-9] x [0-9] lattice\b|\b81 x 2\b|\b0\.65 kB\b",
     "the flow samples beside each crop: 9 x 9 points x 2 float32"),
    (r"\b\d+ channels\b|\b\d+ box corners\b|\b8 projected\b", "tensor and box shapes"),
    (r"\bclipped to 50 px\b", "the clipped input's definition (model.INPUT_MODES)"),
    (r"\(0 = straight along it, 90 = across\)|\bwithin 30 degrees\b",
     "the angle to the line of sight (blind_spots.RADIAL_DEG)"),
    (r"\bat 30, 50 and 70 m\b", "chapter 09's signal table: the band's ends and middle"),
    (r"\bwithin 0\.5 m/s\b", "chapter 04's examples near the threshold (EXAMPLE_BAND)"),
    (r"\bat most 0\.80\b", "the world's difficulty target (difficulty.TARGET_F1)"),
    (r"\bat 0\.5 a quarter\b", "flow_scale arithmetic: 0.5 x 0.5 of the pixels"),
    (r"\b10 m distance\b|\b0 to 100 m\b", "the distance bins of Table 4's breakdown"),
    (r"^0-$", "the near end of Table 4's range in its rows' names (ch08_generalisation.table4)"),
    (r"\bPython 3\.\d+\+|\bJupyter Book \d\b", "versions of the tools, by name"),
    (r"\bat most 15 lines\b|\bat most 76 characters\b",
     "the notebook style the tests enforce (tests/test_notebooks.py)"),
    (r"\bfrom 0 to CODE\b|\b1 / CODE\b", "a range or a formula over a parameter"),
    (r"\b20-80 m\b|\b8-pixel\b|\bevery 500\b|\b10\^4 to 10\^5\b",
     "FastFlowNet's architecture and the shipped weights' recipe (their manifest)"),
)


def prose(text: str) -> str:
    """What a reader reads as words: code (fenced and inline, shown as CODE), glue roles,
    math, link targets, URLs, comments, identifiers holding digits (ResNet18, F1, 3D,
    float16) and references to numbered things (Table 3, chapter 07, frame 1) removed."""
    text = re.sub(r"```.*?```", " ", text, flags=re.S)
    text = re.sub(r"<!--.*?-->", " ", text, flags=re.S)
    text = re.sub(r"\{glue:[a-z]+\}`[^`]*`|\{[a-z]+\}`[^`]*`", " GLUED ", text)
    text = re.sub(r"`[^`]*`", " CODE ", text)
    text = re.sub(r"\$[^$]*\$|\]\([^)]*\)|https?://\S+", " ", text)
    text = re.sub(r"(?m)^\s*\d+\. |^\|\s*\d\d\b", " ", text)  # list items, chapters' rows
    text = re.sub(r"\([A-Z](?:, ?(?:[A-Z]|\d+))+\)", " SHAPE ", text)  # (N, 2, S, S)
    text = re.sub(r"\b(?:[Tt]ables?|[Ff]igures?|[Cc]hapters?|[Ee]quations?|[Pp]hases?|"
                  r"[Ff]rames?|[Ff]olds?|[Ss]ections?|[Ss]teps?|[Ss]eeds?|position|timestamp)"
                  r"[ -]\d+(?:\s*(?:-|->|to|and|,|or)\s*\d+)*", " ", text)
    text = re.sub(r"\b\w*[A-Za-z_]\d[\w.]*|\b\d+[A-Za-z_]\w*", " ", text)
    return " ".join(text.split())


def stray_numbers(text: str, code: str = "") -> list[str]:
    """The numbers of ``text``'s prose that are neither DEFINED nor in ``code`` (the code
    shown beside it) nor a parameter's value restated after it (``CODE = 1``), each with
    its context."""
    words = prose(text)
    for pattern, _ in DEFINED:
        words = re.sub(pattern, " ", words)
    words = re.sub(r"CODE\s*(?:=|>|<|>=|<=)\s*\d+(?:\.\d+)?", " ", words)
    shown = set(re.findall(r"\d+(?:\.\d+)?", code))
    out = []
    for m in re.finditer(r"(?<![\w.])\d+(?:[.,]\d+)*", words):
        if m.group() not in shown:
            out.append(" ".join(words[max(0, m.start() - 40):m.end() + 20].split()))
    return out


def _cells(nb: Path) -> list[tuple[str, str]]:
    """(prose, code shown in it) of each markdown cell."""
    out = []
    for cell in json.loads(nb.read_text())["cells"]:
        if cell["cell_type"] == "markdown":
            text = "".join(cell["source"])
            code = " ".join(re.findall(r"```.*?```|`[^`]*`", text, flags=re.S))
            out.append((text, code))
    return out


@pytest.mark.parametrize("nb", NOTEBOOKS, ids=lambda p: p.stem)
def test_a_notebook_s_prose_types_no_measurement(nb):
    stray = [s for text, code in _cells(nb) for s in stray_numbers(text, code)]
    assert not stray, (f"{nb.name}: numbers typed in prose (glue them from the run, or add "
                       f"a definition to DEFINED with its reason): {stray}")


def _strings(path: Path) -> list[tuple[int, str]]:
    """(line, text) of every string literal of a module that is not a docstring (the
    literal parts of f-strings included)."""
    tree = ast.parse(path.read_text())
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef)) and n.body
            and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    return [(n.lineno, n.value) for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs]


#: Backend strings that are names, not measurements: table headers' bins and keys.
BACKEND_NAMES = re.compile(r"^\d+-\d+ %$|^\d+$|^\d{2}$")


@pytest.mark.parametrize("path", BACKENDS, ids=lambda p: p.stem)
def test_a_chapter_backend_s_words_type_no_measurement(path):
    stray = [f"line {line}: {s}" for line, text in _strings(path)
             if not BACKEND_NAMES.match(text.strip()) for s in stray_numbers(text)]
    assert not stray, f"{path.name}: numbers typed in the book's words: {stray}"


def _blocks(text: str) -> list[str]:
    """A Markdown file's paragraphs, tables and list items, code removed."""
    out = []
    for b in re.split(r"\n\s*\n", re.sub(r"```.*?```", "", text, flags=re.S)):
        out += [item for item in re.split(r"\n(?=- |\d+\. )", b) if item.strip()]
    return out


def test_the_readme_s_numbers_are_definitions_or_cite_their_record():
    """A README block with a measured number names the benchmarks/*.md record it is from."""
    stray = [s for b in _blocks((ROOT / "README.md").read_text())
             if "benchmarks/" not in b for s in stray_numbers(b)]
    assert not stray, f"README.md: numbers without their record: {stray}"


@pytest.mark.parametrize(("text", "code", "bad"), [
    ("after epoch 10 the StepLR schedule halves the rate", "", ["10"]),  # chapter 06's old
    ("Table 3 of chapter 07 on ResNet18 in float16, F1 at 95 % over 3D boxes", "", []),
    ("with a 3 m/s threshold", "--set speed_threshold=3", []),       # restates the command
    ("with a 3 m/s threshold", "", ["3"]),
    ("vehicles up to `general_max_distance` (70 m)", "", ["70"]),
    ("With `folds` = 1 the split", "", []),
    ("{glue:text}`n_scenes:.0f` scenes, about 6 minutes", "", ["6"]),
])
def test_the_check_tells_a_typed_number_from_a_definition(text, code, bad):
    got = [re.findall(r"\d+", s) for s in stray_numbers(text, code)]
    assert [n for g in got for n in g if n in bad] == bad and len(got) == len(bad)
