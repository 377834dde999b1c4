"""Words of real PDFs found as pdftotext finds them: the figures of docs/importing.md's table.

Run from the repository root (a seeded plain script, not a test; needs poppler-utils)::

    .venv/bin/python -m benchmarks.pdf_words                  # the Debian manuals installed
    .venv/bin/python -m benchmarks.pdf_words a.pdf b.pdf.gz --sample 500 --seed 2 --misses

For each PDF: its text by ``pdftotext`` (poppler), the oracle, which joins words broken
across lines; its items as ``vantage import`` reads them, built into a snapshot as an import
builds it. From pdftotext's text, a seeded sample of distinct words (three letters or more,
an apostrophe within allowed); each word's hits in Vantage (the search's ``total``) against
its occurrences in pdftotext's text, both folded as search folds (substrings, left to right,
not overlapping, as the search counts them). pdftotext leaves some letter-spaced words spaced
out (a code listing's ``b u f f e r``), which Vantage reads whole: a second count adds those
(the word's letters one space apart in pdftotext's text, a space on either side). Then every word of pdftotext's text
holding a curly apostrophe, typed with a straight one. Prints a Markdown table: the PDF, who
made it, its pages, the words sampled, how many Vantage counts as pdftotext does (and as it
does with its spaced-out letters read whole), how many it never finds though pdftotext has
them, and the straight apostrophes that find their curly form.
"""

from __future__ import annotations

import argparse
import gzip
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.importers import Source, batches, detect
from app.search import search
from app.snapshots import Snapshot, build
from app.table import ItemTable
from app.text import fold

# The manuals Debian's packages ship, of several producers: (package, file); then a LibreOffice
# document hyphenated as Writer hyphenates, kept in the repository (tests/corpus/hyphenated.py).
ROOT = Path(__file__).resolve().parent.parent
LIBREOFFICE = ROOT / "tests" / "corpus" / "hyphenated.pdf"
CORPUS = [
    ("nettle-dev", "/usr/share/doc/nettle-dev/nettle.pdf.gz"),
    ("zlib1g-dev", "/usr/share/doc/zlib1g-dev/crc-doc.1.0.pdf.gz"),
    ("bzip2-doc", "/usr/share/doc/bzip2/manual.pdf.gz"),
    ("valgrind", "/usr/share/doc/valgrind/valgrind_manual.pdf.gz"),
    ("libtasn1-doc", "/usr/share/doc/libtasn1-doc/libtasn1.pdf"),
    ("fontconfig", "/usr/share/doc/fontconfig/fontconfig-user.pdf.gz"),
    ("shared-mime-info", "/usr/share/doc/shared-mime-info/shared-mime-info-spec.pdf"),
    ("", str(LIBREOFFICE)),
]
SAMPLE = 300  # distinct words a PDF
WORD = re.compile(r"[^\W\d_]{3,}(?:['’][^\W\d_]+)?")
CURLY = re.compile(r"[^\W\d_]+’[^\W\d_]+")
TEXT_ID = re.compile(r"p\d+w\d+")  # a word's id, as the PDF importer names it
UNEVEN = 1.15  # words of a line further apart in height than this make it uneven


@dataclass
class Figures:
    """One PDF's figures: the sampled words' counts, and the curly apostrophes'."""

    name: str
    producer: str
    pages: int
    # word: (pdftotext's count, with its spaced-out letters read whole, Vantage's)
    counts: dict[str, tuple[int, int, int]] = field(default_factory=dict)
    apostrophes: dict[str, tuple[int, int]] = field(default_factory=dict)  # typed straight: (theirs, ours)
    lines: int = 0  # of two words or more
    uneven: int = 0  # of them, holding words over UNEVEN apart in height
    seconds: float = 0.0

    @property
    def same(self) -> int:
        return sum(theirs == ours for theirs, _, ours in self.counts.values())

    @property
    def same_spaced(self) -> int:
        """Counted as pdftotext counts, its spaced-out letters read whole."""
        return sum(spaced == ours for _, spaced, ours in self.counts.values())

    @property
    def never(self) -> list[str]:
        return [w for w, (theirs, _, ours) in self.counts.items() if theirs and not ours]

    @property
    def found(self) -> int:
        """Straight-typed apostrophes that find their curly form."""
        return sum(ours > 0 for _, ours in self.apostrophes.values())


@contextmanager
def plain(path: Path) -> Iterator[Path]:
    """``path``, or a gzipped PDF decompressed into a temporary file (pdftotext reads no gzip)."""
    with path.open("rb") as file:
        zipped = file.read(2) == b"\x1f\x8b"
    if not zipped:
        yield path
        return
    with tempfile.TemporaryDirectory() as scratch:
        out = Path(scratch) / path.name.removesuffix(".gz")
        with gzip.open(path) as source, out.open("wb") as sink:
            shutil.copyfileobj(source, sink)
        yield out


def pdftotext(path: Path) -> str:
    """The PDF's text as pdftotext reads it (UTF-8, reading order).

    :raises FileNotFoundError: if pdftotext is not installed (apt-get install poppler-utils)
    """
    with plain(path) as pdf:
        return subprocess.run(
            ["pdftotext", "-enc", "UTF-8", str(pdf), "-"], capture_output=True, check=True
        ).stdout.decode()


def info(path: Path) -> tuple[str, int]:
    """The PDF's producer (its Creator and Producer) and its pages, as pdfinfo says."""
    with plain(path) as pdf:
        said = subprocess.run(["pdfinfo", str(pdf)], capture_output=True, text=True).stdout
    fields = dict(line.split(":", 1) for line in said.splitlines() if ":" in line)
    creator, producer = fields.get("Creator", "").strip(), fields.get("Producer", "").strip()
    producer = re.sub(r" Version .*", "", producer)  # Apache FOP Version SVN branches/...: Apache FOP
    if not creator or creator in producer or producer in creator:
        return max(creator, producer, key=len), int(fields.get("Pages", "0") or 0)
    made = f"{creator}, {producer}"
    return made, int(fields.get("Pages", "0") or 0)


def read(path: Path) -> tuple[list[str], np.ndarray, list[bytes]]:
    """The PDF's items as ``vantage import`` reads them (gzipped too), in reading order: their
    ids, boxes and bodies."""
    ids, boxes, bodies = [], [], []
    for batch in batches(Source.of(path), detect(path), 1 << 20, 1 << 16):
        ids += batch.ids
        boxes.append(batch.boxes)
        bodies += batch.bodies
    return ids, np.concatenate(boxes), bodies


def snapshot(path: Path, items: tuple[list[str], np.ndarray, list[bytes]] | None = None) -> Snapshot:
    """The PDF's items (``read``'s, unless given) built into a snapshot as an import builds."""
    return build(ItemTable.of(*(items or read(path))), 1, None)


def uneven_lines(ids: list[str], boxes: np.ndarray) -> tuple[int, int]:
    """How many lines of two words or more, and how many of them hold words over UNEVEN apart
    in height (a page drawing text by its height would draw some of the line as text, some as
    bars). A line: words in reading order, each right of the one before and beside it (their
    vertical centres within each other's boxes)."""
    lines = uneven = 0
    line: list[float] = []
    last = None
    for name, (x0, y0, x1, y1) in zip(ids, boxes.tolist(), strict=True):
        if not TEXT_ID.fullmatch(name):
            continue
        beside = (
            last is not None
            and x0 >= last[2]
            and last[1] < (y0 + y1) / 2 < last[3]
            and y0 < (last[1] + last[3]) / 2 < y1
        )
        if not beside:
            lines, uneven = (
                lines + (len(line) > 1),
                uneven + (len(line) > 1 and max(line) > UNEVEN * min(line)),
            )
            line = []
        line.append(y1 - y0)
        last = (x0, y0, x1, y1)
    return lines + (len(line) > 1), uneven + (len(line) > 1 and max(line) > UNEVEN * min(line))


def words(text: str, sample: int, seed: int) -> list[str]:
    """A seeded sample of the distinct words of ``text`` (folded), three letters or more."""
    distinct = sorted({fold(w) for w in WORD.findall(text)})
    return random.Random(seed).sample(distinct, min(sample, len(distinct)))


def measure(path: Path, sample: int = SAMPLE, seed: int = 1) -> Figures:
    """``path``'s figures: see the module's docstring."""
    started = time.perf_counter()
    producer, pages = info(path)
    oracle = pdftotext(path)
    folded = fold(oracle)
    items = read(path)
    snap = snapshot(path, items)
    figures = Figures(path.name.removesuffix(".gz"), producer, pages)
    figures.lines, figures.uneven = uneven_lines(*items[:2])
    for word in words(oracle, sample, seed):
        theirs = folded.count(word)
        spaced = theirs + len(re.findall(rf"(?<!\S){re.escape(' '.join(word))}(?!\S)", folded))
        figures.counts[word] = (theirs, spaced, search(snap, word, 1).total)
    for word in sorted(set(CURLY.findall(oracle))):
        typed = word.replace("’", "'")
        figures.apostrophes[typed] = (folded.count(fold(typed)), search(snap, typed, 1).total)
    figures.seconds = time.perf_counter() - started
    return figures


def table(rows: list[Figures]) -> str:
    out = [
        "| PDF | made by | pages | words sampled | same count as pdftotext | same, its spaced-out "
        "letters read whole | never found | straight ' finds ’ | lines of uneven words |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for f in rows:
        n = len(f.counts)
        share = f"{f.same} ({100 * f.same / n:.1f}%)" if n else "-"
        spaced = f"{f.same_spaced} ({100 * f.same_spaced / n:.1f}%)" if n else "-"
        curly = f"{f.found} of {len(f.apostrophes)}" if f.apostrophes else "none in it"
        out.append(
            f"| {f.name} | {f.producer} | {f.pages} | {n} | {share} | {spaced} | {len(f.never)} | {curly} "
            f"| {f.uneven} of {f.lines} ({100 * f.uneven / max(f.lines, 1):.1f}%) |"
        )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.pdf_words", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument(
        "paths", nargs="*", type=Path, help="PDFs, gzipped or not (default: the Debian manuals installed)"
    )
    parser.add_argument(
        "--sample", type=int, default=SAMPLE, help="distinct words a PDF (default %(default)s)"
    )
    parser.add_argument("--seed", type=int, default=1, help="the sample's seed (default %(default)s)")
    parser.add_argument(
        "--misses", action="store_true", help="list each word counted otherwise, with both counts"
    )
    args = parser.parse_args(argv)
    if shutil.which("pdftotext") is None:
        parser.exit(2, "pdftotext is missing: apt-get install poppler-utils\n")
    paths = args.paths or [Path(p) for _, p in CORPUS if Path(p).exists()]
    packages = {Path(p): package for package, p in CORPUS}
    missing = [f"{p} ({package})" for package, p in CORPUS if not args.paths and not Path(p).exists()]
    if missing:
        print(f"not installed, left out: {', '.join(missing)}", file=sys.stderr)
    rows = []
    for path in paths:
        figures = measure(path, args.sample, args.seed)
        if packages.get(path):
            figures.name += f" ({packages[path]})"
        rows.append(figures)
        print(f"{figures.name}: {figures.seconds:.1f} s", file=sys.stderr)
        if args.misses:
            for word, (theirs, spaced, ours) in sorted(figures.counts.items()):
                if ours not in (theirs, spaced):
                    print(
                        f"  {word!r}: pdftotext {theirs} ({spaced} spaced out), vantage {ours}",
                        file=sys.stderr,
                    )
            for word, (theirs, ours) in sorted(figures.apostrophes.items()):
                if theirs != ours:
                    print(f"  {word!r} (typed straight): pdftotext {theirs}, vantage {ours}", file=sys.stderr)
    print(table(rows))


if __name__ == "__main__":
    main()
