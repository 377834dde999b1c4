"""PDFs written by hand, byte for byte, to test the PDF importer on what real producers do:
text in the standard fonts placed by content streams the test writes (``Td``, ``Tj``, ``TJ``
kerning, ``Tc`` letter spacing, a font changed mid-word), and a font whose ToUnicode map says
which character a code is (a soft hyphen, U+2010, U+FFFE).

>>> pdf = document([page("BT /F1 12 Tf 72 700 Td (Hello) Tj ET")])
>>> pdf[:8], pdf.rstrip().endswith(b"%%EOF")
(b'%PDF-1.4', True)
"""

from __future__ import annotations

__all__ = ["FONTS", "HELVETICA", "NARROW_W", "document", "line", "page", "width"]

# The fonts every page has: F1 Helvetica, F2 Helvetica-Bold, F3 Times-Roman, F4 Courier; F5
# Helvetica whose ToUnicode map says the code of "-" (0x2D) is U+2010, F6 that it is a soft
# hyphen (U+00AD), F7 that it is U+FFFE; F8 Helvetica whose widths say "W" is 0.6 em wide, not
# 0.944 (as a math italic's leave out its overhang): text moved on past it by its true width
# (``[(W) -344 (o)] TJ``) draws "Wo" as it should, where PDFium sees a gap and makes up a space.
FONTS = {
    "F1": ("Helvetica", None),
    "F2": ("Helvetica-Bold", None),
    "F3": ("Times-Roman", None),
    "F4": ("Courier", None),
    "F5": ("Helvetica", 0x2010),
    "F6": ("Helvetica", 0x00AD),
    "F7": ("Helvetica", 0xFFFE),
    "F8": ("Helvetica", None),
}
NARROW_W = "F8"
# Helvetica's widths of the codes 32-126 (its AFM), in thousandths of an em
HELVETICA = [
    278, 278, 355, 556, 556, 889, 667, 191, 333, 333, 389, 584, 278, 333, 278, 278,
    556, 556, 556, 556, 556, 556, 556, 556, 556, 556, 278, 278, 584, 584, 584, 556,
    1015, 667, 667, 722, 722, 667, 611, 778, 722, 278, 500, 667, 556, 833, 722, 778,
    667, 778, 722, 667, 611, 722, 667, 944, 667, 667, 611, 278, 278, 278, 469, 556,
    333, 556, 556, 500, 556, 556, 278, 556, 556, 222, 222, 500, 222, 833, 556, 556,
    556, 556, 333, 500, 278, 556, 500, 722, 500, 500, 500, 334, 260, 334, 584,
]  # fmt: skip


def line(x: float, y: float, text: str, font: str = "F1", size: float = 12) -> str:
    """A content stream's text object drawing ``text`` (Latin-1) with its baseline at (x, y)."""
    return f"BT /{font} {size} Tf {x} {y} Td ({_escaped(text)}) Tj ET"


def width(text: str, size: float = 12) -> float:
    """How far Helvetica at ``size`` moves on over ``text`` (ASCII), in points."""
    return sum(HELVETICA[ord(ch) - 32] for ch in text) * size / 1000


def page(*content: str) -> str:
    """A page's content stream: its text objects (and other operators), one a line."""
    return "\n".join(content)


def document(pages: list[str], size: tuple[float, float] = (612, 792)) -> bytes:
    """A PDF of ``pages`` (their content streams), each of ``size`` points."""
    objects: list[bytes] = []

    def add(body: bytes) -> int:
        objects.append(body)
        return len(objects)

    catalog = add(b"")  # filled in once the pages' object is known
    pages_at = add(b"")
    fonts = {}
    for name, (base, hyphen) in FONTS.items():
        font = f"<< /Type /Font /Subtype /Type1 /BaseFont /{base} /Encoding /WinAnsiEncoding"
        if hyphen is not None:
            font += f" /ToUnicode {add(_stream(_cmap(hyphen)))} 0 R"
        if name == NARROW_W:
            widths = [600 if code == ord("W") else w for code, w in enumerate(HELVETICA, 32)]
            font += f" /FirstChar 32 /LastChar 126 /Widths [{' '.join(map(str, widths))}]"
        fonts[name] = add((font + " >>").encode())
    resources = "<< /Font << " + " ".join(f"/{n} {k} 0 R" for n, k in fonts.items()) + " >> >>"
    kids = []
    for content in pages:
        stream = add(_stream(content.encode("latin-1")))
        kids.append(
            add(
                f"<< /Type /Page /Parent {pages_at} 0 R /MediaBox [0 0 {size[0]} {size[1]}] "
                f"/Resources {resources} /Contents {stream} 0 R >>".encode()
            )
        )
    objects[catalog - 1] = f"<< /Type /Catalog /Pages {pages_at} 0 R >>".encode()
    objects[pages_at - 1] = (
        f"<< /Type /Pages /Kids [{' '.join(f'{k} 0 R' for k in kids)}] /Count {len(kids)} >>".encode()
    )
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for number, body in enumerate(objects, 1):
        offsets.append(len(out))
        out += f"{number} 0 obj\n".encode() + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objects) + 1}\n0000000000 65535 f \n".encode()
    out += b"".join(f"{at:010d} 00000 n \n".encode() for at in offsets)
    out += f"trailer\n<< /Size {len(objects) + 1} /Root {catalog} 0 R >>\nstartxref\n{xref}\n%%EOF\n".encode()
    return bytes(out)


def _stream(data: bytes) -> bytes:
    return f"<< /Length {len(data)} >>\nstream\n".encode() + data + b"\nendstream"


def _cmap(hyphen: int) -> bytes:
    """A ToUnicode map: each printable WinAnsi code its Latin-1 character, "-" ``hyphen``."""
    ranges = [(0x20, 0x2C), (0x2E, 0x7E)]
    body = "\n".join(f"<{a:02X}> <{b:02X}> <{a:04X}>" for a, b in ranges)
    return (
        "/CIDInit /ProcSet findresource begin 12 dict begin begincmap\n"
        "/CIDSystemInfo << /Registry (Adobe) /Ordering (UCS) /Supplement 0 >> def\n"
        "/CMapName /Vantage-Test def /CMapType 2 def\n"
        "1 begincodespacerange <00> <FF> endcodespacerange\n"
        f"{len(ranges)} beginbfrange\n{body}\nendbfrange\n"
        f"1 beginbfchar\n<2D> <{hyphen:04X}>\nendbfchar\n"
        "endcmap CMapName currentdict /CMap defineresource pop end end"
    ).encode()


def _escaped(text: str) -> str:
    return text.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)")
