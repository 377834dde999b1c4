"""Writes ``hyphenated.fodt``, the source of ``hyphenated.pdf``: a LibreOffice document for the
PDF corpus test (tests/test_pdf_words.py), set as LibreOffice sets text people write in it:
justified in a narrow column with automatic hyphenation (English, US), so long words and
identifiers break at line ends (``configu-``/``ration``, ``ChangeStart-``/``ingValue``), with
curly quotes and apostrophes, compounds (``object-oriented``, ``Well-known``) and ranges
(``12–15``). Regenerate both, from this directory, with LibreOffice Writer and its US English
hyphenation patterns (``apt-get install libreoffice-writer-nogui hyphen-en-us``)::

    python3 hyphenated.py && soffice --headless --convert-to pdf hyphenated.fodt
"""

import random
from pathlib import Path
from xml.sax.saxutils import escape

PROSE = (  # the long words every paragraph is made of
    "the configuration of every implementation depends on responsibilities shared between "
    "independent components; internationalization and accessibility requirements demand "
    "considerable documentation, especially where the interoperability of asynchronous "
    "notifications, authentication, synchronization and representation is concerned"
)
SENTENCES = [
    "The library’s “object-oriented” interface doesn’t hide its state; it’s documented on pages 12–15.",
    "An administrator’s checklist covers encapsulation, serialization and the characteristic cases.",
    "Don’t rely on “magic” defaults: the framework’s compatibility guarantees were revised in 2008–2010.",
    "Well-known identifiers such as ChangeStartingValue appear in code; they’re searched whole.",
]
STYLES = """ <office:styles>
  <style:style style:name="Body" style:family="paragraph">
   <style:paragraph-properties fo:text-align="justify" fo:margin-bottom="0.2cm"/>
   <style:text-properties fo:font-size="11pt" fo:language="en" fo:country="US" fo:hyphenate="true"
     fo:hyphenation-remain-char-count="2" fo:hyphenation-push-char-count="2"/>
  </style:style>
 </office:styles>
 <office:automatic-styles>
  <style:page-layout style:name="Narrow">
   <style:page-layout-properties fo:page-width="14.8cm" fo:page-height="21cm" fo:margin-top="2cm"
     fo:margin-bottom="2cm" fo:margin-left="3cm" fo:margin-right="3cm"/>
  </style:page-layout>
 </office:automatic-styles>
 <office:master-styles><style:master-page style:name="Standard" style:page-layout-name="Narrow"/></office:master-styles>
"""
NAMESPACES = " ".join(
    f'xmlns:{name}="urn:oasis:names:tc:opendocument:xmlns:{urn}:1.0"'
    for name, urn in [("office", "office"), ("style", "style"), ("text", "text"), ("fo", "xsl-fo-compatible")]
)


def paragraphs(count: int = 14, seed: int = 7) -> list[str]:
    """``count`` paragraphs of long words, each ending with two of SENTENCES (seeded)."""
    rng, words = random.Random(seed), PROSE.split()
    out = []
    for _ in range(count):
        prose = " ".join(rng.choice(words) for _ in range(rng.randint(45, 80)))
        out.append(f"{prose.capitalize()}. {' '.join(rng.sample(SENTENCES, 2))}")
    return out


def main() -> None:
    body = "\n".join(f'<text:p text:style-name="Body">{escape(p)}</text:p>' for p in paragraphs())
    Path(__file__).with_suffix(".fodt").write_text(
        f'<?xml version="1.0" encoding="UTF-8"?>\n<office:document {NAMESPACES} office:version="1.3"'
        f' office:mimetype="application/vnd.oasis.opendocument.text">\n{STYLES}'
        f" <office:body><office:text>\n{body}\n </office:text></office:body>\n</office:document>\n"
    )


if __name__ == "__main__":
    main()
