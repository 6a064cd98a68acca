"""`make docs` (pdoc, numpy docstring format) renders the public API: a module's page holds its
public names and the numpydoc sections as headings, not as raw underlined text."""

import pytest

pdoc = pytest.importorskip("pdoc")


def test_fitting_api_page_renders_numpydoc():
    import pdoc.render

    pdoc.render.configure(docformat="numpy", show_source=False)
    html = pdoc.pdoc("gonio.fitting.formats")
    for name in ("mitsuba_document", "write_pabopto", "read_merl"):
        assert f'id="{name}"' in html, name
    assert ">Parameters</h6>" in html and ">Returns</h6>" in html
    assert "----------" not in html           # numpydoc underlines became headings
