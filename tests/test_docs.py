"""Citations resolve inside the repository: every document the code, the tests or the READMEs cite by
section (``docs/algorithms.md §5.8``) exists, has that section, and nothing cites a spec outside it."""

import io
import re
import tokenize
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCE_DIRS = ("xrl_jax", "envs", "experiments", "tests")
MARKDOWN = ("README.md", "tests/data/README.md")

DOC_PATH = re.compile(r"(?<![\w/.-])((?:docs|tests/data)/[\w.-]+\.md)")
BARE_DOC = re.compile(r"(?<![\w/.-])((?:algorithms|carenv-[\w-]+|README)\.md)")
SECTION = re.compile(r"§\s?(\d+(?:\.\d+)*)")
APPENDIX = re.compile(r"\bAppendix ([A-Z])\b")
QUIRK = re.compile(r"\bQ(\d{1,2})\b")
# Citations of documents that a clone does not have: "spec §3", "spec/algorithms.md", "the spec's",
# "Spec:", "golden README".
OUTSIDE = re.compile(r"\bspec\b|\bgolden README\b", re.IGNORECASE)
QUIRK_DOC = "docs/carenv-intersection.md"


def _text_chunks(path: Path):
    """(line, text) of every comment and string literal of a Python file, or every line of a Markdown
    file: the places where citations live (code identifiers such as ``importlib.util.spec_...`` are not)."""
    text = path.read_text(encoding="utf-8")
    if path.suffix == ".md":
        return [(i + 1, line) for i, line in enumerate(text.splitlines())]
    kinds = {tokenize.COMMENT, tokenize.STRING}
    if hasattr(tokenize, "FSTRING_MIDDLE"):
        kinds.add(tokenize.FSTRING_MIDDLE)
    return [
        (tok.start[0], tok.string)
        for tok in tokenize.generate_tokens(io.StringIO(text).readline)
        if tok.type in kinds
    ]


def _files():
    files = [ROOT / name for name in MARKDOWN]
    for folder in SOURCE_DIRS:
        files += sorted((ROOT / folder).rglob("*.py"))
    return [f for f in files if f.exists() and f.resolve() != Path(__file__).resolve()]


@cache
def _headings(doc: str):
    """Section numbers ("5", "5.8") and appendix letters of a cited Markdown document."""
    numbers, appendices = set(), set()
    for line in (ROOT / doc).read_text(encoding="utf-8").splitlines():
        if match := re.match(r"#+\s+(\d+(?:\.\d+)*)\.?\s", line):
            numbers.add(match.group(1))
        elif match := re.match(r"#+\s+Appendix ([A-Z])\b", line):
            appendices.add(match.group(1))
    return numbers, appendices


@cache
def _quirks(doc: str):
    return {int(m) for m in re.findall(r"^Q(\d+)\.", (ROOT / doc).read_text(encoding="utf-8"), re.M)}


def _section_exists(doc: str, number: str) -> bool:
    numbers, _ = _headings(doc)
    parts = number.split(".")
    # §7.2.7 = item 7 of the numbered list of §7.2; a plain §8.6 must be a heading.
    return number in numbers or (len(parts) >= 3 and ".".join(parts[:2]) in numbers)


def _where(path: Path, line: int) -> str:
    return f"{path.relative_to(ROOT)}:{line}"


def _citations():
    """Yield (file, line, governing document or None, kind, value, file's documents) per reference."""
    for path in _files():
        chunks = _text_chunks(path)
        cited = sorted({m for _, text in chunks for m in DOC_PATH.findall(text)})
        for line, text in chunks:
            events = sorted(
                [(m.start(), "doc", m.group(1)) for m in DOC_PATH.finditer(text)]
                + [(m.start(), "section", m.group(1)) for m in SECTION.finditer(text)]
                + [(m.start(), "appendix", m.group(1)) for m in APPENDIX.finditer(text)]
            )
            current = None
            for _, kind, value in events:
                if kind == "doc":
                    current = value
                else:
                    yield path, line, current, kind, value, cited


def test_no_citation_of_documents_outside_the_repository():
    bad = []
    for path in _files():
        for line, text in _text_chunks(path):
            for match in OUTSIDE.finditer(text):
                bad.append(f"{_where(path, line)}: {match.group(0)!r} in {text.strip()[:100]!r}")
            for match in BARE_DOC.finditer(text):
                if not text[: match.start()].endswith(("docs/", "tests/data/")):
                    bad.append(f"{_where(path, line)}: {match.group(1)} without its folder (docs/...)")
    assert not bad, "citations that a clone cannot follow:\n" + "\n".join(bad)


def test_cited_documents_exist():
    missing = []
    for path in _files():
        for line, text in _text_chunks(path):
            absent = [d for d in DOC_PATH.findall(text) if not (ROOT / d).is_file()]
            missing += [f"{_where(path, line)}: {d}" for d in absent]
    assert not missing, "cited documents missing from the repository:\n" + "\n".join(missing)


def test_every_section_reference_resolves():
    bad = []
    for path, line, doc, kind, value, cited in _citations():
        docs = [doc] if doc else [d for d in cited if (ROOT / d).is_file()]
        if not docs:
            bad.append(f"{_where(path, line)}: §{value} but the file cites no document in docs/")
            continue
        if kind == "section":
            ok = any(_section_exists(d, value) for d in docs)
        else:
            ok = any(value in _headings(d)[1] for d in docs)
        if not ok:
            label = f"§{value}" if kind == "section" else f"Appendix {value}"
            bad.append(f"{_where(path, line)}: {label} is not a section of {' or '.join(docs)}")
    assert not bad, "section references that do not resolve:\n" + "\n".join(bad)


def test_intersection_quirk_labels_exist():
    """Q1..Q16 are the numbered quirks of docs/carenv-intersection.md §9."""
    bad = []
    for path in _files():
        chunks = _text_chunks(path)
        if not any(QUIRK_DOC in text for _, text in chunks):
            continue
        for line, text in chunks:
            labels = map(int, QUIRK.findall(text))
            bad += [f"{_where(path, line)}: Q{q}" for q in labels if q not in _quirks(QUIRK_DOC)]
    assert not bad, f"quirk labels missing from {QUIRK_DOC} §9:\n" + "\n".join(bad)


def test_the_checks_catch_what_they_are_for():
    assert all(OUTSIDE.search(s) for s in ("(spec §5.3)", "spec/algorithms.md", "Spec: x", "golden README"))
    assert not OUTSIDE.search("unspecified, specified, inspect, timespec, spec_from_file_location")
    assert _section_exists("docs/algorithms.md", "5.8") and _section_exists("docs/algorithms.md", "0")
    assert _section_exists("docs/algorithms.md", "7.2.7")  # item 7 of §7.2
    assert not _section_exists("docs/algorithms.md", "8.6")  # §8 has items, not subsections: "§8 item 6"
    assert not _section_exists("docs/carenv-single-agent.md", "12")
    assert "A" in _headings("docs/algorithms.md")[1]
    assert _quirks(QUIRK_DOC) == set(range(1, 17))


def test_the_papers_published_numbers_are_well_formed():
    """docs/paper_results.json: each number names a known env, agent and summary metric (the keys
    the run summaries use, so a report can set them side by side), its source, and a CI around it."""
    import json

    from xrl_jax.config import ALGOS, ENVS
    from xrl_jax.runs import summary_metrics

    data = json.loads((ROOT / "docs" / "paper_results.json").read_text())
    assert len(data["results"]) >= 10
    for row in data["results"]:
        assert row["env"] in ENVS and row["algo"] in ALGOS and row["source"], row
        assert row["metric"] in dict(summary_metrics(row["env"])), row
        if row["ci"] is not None:
            low, high = row["ci"]
            assert low <= row["iqm"] <= high, row
    for row in data["table_1_country_road_continuous"]:
        low, high = row["return_ci"]
        assert low <= row["return_iqm"] <= high and row["flops"] > 0 and row["params"] > 0
