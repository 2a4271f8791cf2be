"""docs/ccsds.md's dictionary tables are the ones generated from data/dictionary.py."""
from __future__ import annotations

from pathlib import Path

from magstack.data.dictionary_doc import BEGIN, END, dictionary_markdown


def test_docs_tables_equal_the_generated_ones():
    text = (Path(__file__).resolve().parents[1] / "docs" / "ccsds.md").read_text(encoding="utf-8")
    assert text.count(BEGIN) == 1 and text.count(END) == 1
    assert text.split(BEGIN, 1)[1].split(END, 1)[0].lstrip("\n") == dictionary_markdown()
