"""docs/pictures.md shows the pictures `python -m lab.pictures.doc_pictures` writes, and says so."""

from __future__ import annotations

import re

from lab.pictures.doc_pictures import GROUPS, PICTURES, REPO


def test_every_picture_of_the_page_is_regenerated_by_the_script() -> None:
    page = (REPO / "docs" / "pictures.md").read_text(encoding="utf-8")
    shown = set(re.findall(r"\(img/([^)]+\.png)\)", page))
    written = {name for names in PICTURES.values() for name in names}
    assert shown == written, (shown - written, written - shown)
    assert set(PICTURES) == set(GROUPS)
    assert "python -m lab.pictures.doc_pictures" in page  # the one command, said in the doc
    for name in shown:
        assert (REPO / "docs" / "img" / name).is_file(), name
