"""No hand-typed measurement in what a reader reads (issue 39): every number in the
notebooks' prose, the chapter backends' strings and the README is glued from the run, or a
definition (the paper's settings, the data format, the method's constants: DEFINED, each
with its reason), or restates the code beside it (a Try-it command's ``--set``), or, in the
README, sits in a block that cites the dated record it comes from (``benchmarks/*.md``).
A book page (``book/*.md``, issue 50) holds the same rule per sentence and table cell: a
number is glued, a parameter's value beside its name (checked against the demo and paper
profiles), the paper's or the original code's (PAPER, where the unit names them), in the
record it cites with a date the record holds (or the module it names), or a definition
(BOOK_DEFINED, each with its reason). Seconds: text only."""

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


# --- the book's own pages (book/*.md) ---------------------------------------------------

BOOK_PAGES = sorted((ROOT / "book").glob("*.md"))

#: The paper's and the original code's numbers a page may quote, in a sentence or table
#: cell that names the paper or the original code (a column headed so counts): (pattern,
#: where the paper or the code gives it).
PAPER: tuple[tuple[str, str], ...] = (
    (r"\b92\.9 %", "Table 3: FastFlowNet's F1"),
    (r"\bthe paper's 60\b", "Table 2: 60 epochs"),
    (r"\bF1 89\.5 % with precision 89\.7 % and recall 89\.9 %",
     "Table 3: RAFT's F1, precision and recall"),
    (r"\bF1 60\.4 % with precision 63\.0 % and recall 62\.8 %",
     "Table 4: RAFT's F1, precision and recall"),
    (r"\b16467 training and 1993 evaluation objects\b", "its data section's object counts"),
    (r"\b604 usable scenes of 20 s\b", "its data section: nuScenes trainval after filtering"),
    (r"\bevery 10 epochs\b", "Table 2: StepLR's step"),
    (r"\(4 frames apart\)|\b4 frames apart as the paper\b", "Table 4's pairs"),
    (r"^paper: 1$", "one training run a method (its Tables 3 and 4)"),
    (r"\bscored F1 = 0 and recall = 0\b|\bcounted as 0\b|\boriginal's 0\b",
     "the original code: sklearn's zero_division default, 0"),
    (r"\btraining 3 of 5\b", "the original code's thinning of still objects"),
    (r"\b904 rows\b|\boff by 2 px\b", "the original code's RAFT padding of 900 rows"),
    (r"\b6 frames apart\b", "the original code's generalisation pairs"),
    (r"\b1-2 px larger\b", "the original code's floor/ceil crop bounds"),
    (r"\b89\.5 % \(RAFT\)|\b60\.4 %", "Table 3: RAFT's F1; Table 4: its F1 (after the rest)"),
)

#: Definitions a book page may type beyond DEFINED: (pattern, why).
BOOK_DEFINED: tuple[tuple[str, str], ...] = (
    (r"\b\d{4}-\d\d-\d\d\b", "a date: when a record was made, not what it measured"),
    (r"\bRAFT's own default is 12\b", "RAFT's published default (its code's --iters)"),
    (r"\bFl-all 11\.22 %", "FastFlowNet's paper: its KITTI 2015 test result"),
    (r"\b11\.2 M parameters\b", "ResNet18 at the paper's width (torchvision's count)"),
    (r"\(S - 1\) / S\b", "the bootstrap's variance factor, a formula"),
    (r"\b4 times the SGD steps\b", "the paper's batch over the demo's: 128 / 32"),
    (r"\bsign\(x\) log\(1 \+ \\?\|x\\?\|\)", "the log input's formula (model.INPUT_MODES)"),
    (r"\(x / 255 - 0\.5\) / 0\.25\b", "the image channels' standardisation (its formula)"),
    (r"\bz = 0\b|\bat 1000 m\b", "the static-world model's ground and far planes (code)"),
    (r"\ba 2-core CPU\b|\bon 2 (?:CPU )?cores\b", "the machine the demo is sized for"),
    (r"\bthe 50-minute budget\b|\bwithin 50 minutes\b", "the demo's time budget (issue 1)"),
    (r"\ball 8 corners\b", "a 3D box's corners"),
    (r"\b(?:19|20)\d\d(?=\.(?:\s|$)|\)|\s\()", "a year, in a reference"),
    (r"\barXiv:\d+\.\d+", "an arXiv identifier"),
    (r"\bfrom 0 to 70 m\b", "Table 4's range: general_min_distance to general_max_distance"),
    (r"\bat 2-3 m/s\b|\bat 5 m/s or more\b",
     "chapter 09's speed bins (blind_spots.MOVER_SPEED_BINS)"),
    (r"\ba multiple of 8\b", "RAFT's and FastFlowNet's input padding (their strides)"),
    (r"\bweigh (?:21|41) times\b", "1 + the recipe's box_weight (20, 40: pretrain.SCHEDULE)"),
    (r"\b10\^4 to 5 x 10\^4 steps\b", "the published recipes' warm-up (UFlow, SMURF)"),
)


def _values(v: object) -> set[str]:
    """The numbers a parameter's value may be written as: itself, a list's items and
    length, a fraction as a percentage."""
    if isinstance(v, bool) or v is None:
        return set()
    if isinstance(v, (list, tuple)):
        return {str(len(v))}.union(*(_values(x) for x in v))
    if isinstance(v, (int, float)):
        out = {f"{v:g}", f"{float(v):.1f}", f"{v:.0e}".replace("e-0", "e-")}
        if 0 < v < 1:
            out.add(f"{100 * v:g}")
        return out
    return set()


def _settings() -> dict[str, tuple[set[str], list[object]]]:
    """``{name: (numbers it may be written as, [demo value, paper value])}``."""
    from flowmod import params

    demo = params.load_profile("demo").model_dump()
    paper = {**demo, **params.read_profile("paper")}
    return {k: (_values(demo[k]) | _values(paper[k]), [demo[k], paper[k]]) for k in demo}


_NUM = r"(?<![\w.])\d+(?:\.\d+)?(?![\w])"


def _setting_numbers(text: str, settings) -> tuple[str, list[str]]:
    """``text`` with every number that restates a parameter it names replaced by SET, and
    the misquoted settings. A number restates a parameter when its value is one of the demo's
    or paper profile's values of a parameter named near it: before the parenthesis that names
    it (``8 (`epochs`)``, ``20 flow updates (`raft_iters`)``), or in the parenthesis that
    holds the name or follows it (``(`folds`: 3)``, ```general_max_distance` (70 m)``).
    ```name: value``` in code must hold the demo's or the paper profile's value."""
    errors, spans = [], []
    mentions = [(m.start(), m.end(), m.group(1), m.group(2))
                for m in re.finditer(r"`(\w+)(?:\s*[:=]\s*([^`]*))?`", text)
                if m.group(1) in settings]
    for a, b, name, quoted in mentions:
        if quoted is not None and re.fullmatch(r"-?\d+(?:\.\d+)?(?:e-?\d+)?", quoted.strip()):
            if float(quoted) not in [v for v in settings[name][1]
                                     if isinstance(v, (int, float))]:
                errors.append(f"`{name}: {quoted}` is neither the demo's nor the paper's")
        windows = []
        before = re.search(r"(\d+(?:\.\d+)?)(?:\s+[A-Za-z%]+){0,2}\s*\(\s*$", text[:a])
        if before:
            windows.append((before.start(1), before.end(1)))
        opened = text.rfind("(", 0, a)
        if opened >= 0 and ")" not in text[opened:a]:
            close = text.find(")", b)
            windows.append((opened, close if close >= 0 else len(text)))
        after = re.match(r"\s*(?:\w+\s+){0,2}\(([^()]*)\)", text[b:])
        if after:
            windows.append((b + after.start(1), b + after.end(1)))
        for lo, hi in windows:
            near = {n for p, _, n, _ in mentions if lo - 100 <= p <= hi + 100}
            allowed = set().union(*(settings[n][0] for n in near))
            for m in re.finditer(_NUM, text[lo:hi]):
                if m.group() in allowed or f"{float(m.group()):g}" in allowed:
                    spans.append((lo + m.start(), lo + m.end()))
    for lo, hi in sorted(set(spans), reverse=True):
        text = text[:lo] + "SET" + text[hi:]
    return text, errors


_RECORD = re.compile(r"\b(benchmarks/[\w./-]+\.(?:md|json))\b")
_SOURCE = re.compile(r"`(flowmod(?:\.\w+)+)`|\b(weights/[\w./-]+\.json)\b")


def _cited(unit: str) -> tuple[set[str], list[str]]:
    """Numbers of the records and sources a unit cites, and what is wrong with its
    citations. A record (``benchmarks/*.md`` or ``.json``) counts only with a date that the
    record holds; a source is a module (```flowmod.flow.pretrain.SCHEDULE```: the recipe
    in its code) or a committed manifest."""
    numbers: set[str] = set()
    errors = []
    dates = re.findall(r"\b\d{4}-\d\d-\d\d\b", unit)
    for rel in _RECORD.findall(unit):
        path = ROOT / rel
        if not path.is_file():
            errors.append(f"{rel} cited but not committed")
            continue
        body = path.read_text()
        if not any(d in body for d in dates):
            errors.append(f"{rel} cited without a date it holds ({dates or 'no date'})")
            continue
        numbers |= set(re.findall(_NUM, body.replace(",", "")))
    for module, manifest in _SOURCE.findall(unit):
        parts = module.split(".") if module else []
        while parts and not (ROOT / "src" / Path(*parts)).with_suffix(".py").is_file():
            parts.pop()
        path = ((ROOT / "src" / Path(*parts)).with_suffix(".py") if parts
                else ROOT / manifest if manifest else None)
        if path is not None and path.is_file():
            numbers |= set(re.findall(_NUM, re.sub(r"(?<=\d)_(?=\d)", "", path.read_text())))
    return numbers | {f"{float(n):g}" for n in numbers}, errors


def _units(text: str) -> list[str]:
    """A page's sentences and table cells (each cell after its column's header), HTML
    comments and code blocks removed."""
    text = re.sub(r"```.*?```|<!--.*?-->", "\n\n", text, flags=re.S)
    out = []
    for block in re.split(r"\n\s*\n", text):
        rows = [r for r in block.strip().splitlines() if r.startswith("|")]
        if rows and len(rows) == len(block.strip().splitlines()):
            split = [re.split(r"(?<!\\)\|", r.strip().strip("|")) for r in rows]
            head = split[0]
            out += head
            for cells in split[2:]:
                out += [f"{h.strip()}: {c.strip()}" for h, c in zip(head, cells, strict=False)]
            continue
        for item in re.split(r"\n(?=- |\d+\. )", block):
            out += re.split(r"(?<=[^\W\d][.!?])\s+(?=[A-Z*])", " ".join(item.split()))
    return [u for u in out if u.strip()]


def book_stray_numbers(text: str, settings) -> list[str]:
    """The numbers of a book page that are neither glued, nor DEFINED / BOOK_DEFINED, nor a
    parameter's value restated beside its name, nor the paper's (PAPER, where the unit names
    the paper), nor in the dated record or the source the unit cites; and every wrong
    citation or misquoted setting."""
    out = []
    for unit in _units(text):
        cited, errors = _cited(unit)
        out += [f"{e}: {unit[:80]}" for e in errors]
        words, errors = _setting_numbers(unit, settings)
        out += [f"{e}: {unit[:80]}" for e in errors]
        for pattern, _ in BOOK_DEFINED:
            words = re.sub(pattern, " ", words)
        if re.search(r"\bpaper\b|\bpaper's\b|\boriginal\b", unit):
            for pattern, _ in PAPER:
                words = re.sub(pattern, " ", words)
        out += stray_numbers(words, " ".join(cited))
    return out


@pytest.fixture(scope="module")
def settings():
    return _settings()


@pytest.mark.parametrize("page", BOOK_PAGES, ids=lambda p: p.stem)
def test_a_book_page_s_numbers_are_glued_settings_the_paper_s_or_cited(page, settings):
    stray = book_stray_numbers(page.read_text(), settings)
    assert not stray, (f"book/{page.name}: numbers neither glued from a notebook, nor a "
                       f"setting beside its name, nor the paper's (PAPER), nor in the dated "
                       f"record it cites (benchmarks/*.md with its date), nor a definition "
                       f"(BOOK_DEFINED, with its reason): {stray}")
