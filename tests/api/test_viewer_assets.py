"""The Rerun web viewer's index.html as served: quiet in the console unless asked (?log=debug)."""

from __future__ import annotations

import pytest

from slamreplay.api.web.viewer_assets import QUIET, ViewerAssetsError, quiet_index


def test_quiet_script_runs_before_the_viewer() -> None:
    """The script goes in the head, before any script of the page's body (the viewer's among them)."""
    page = '<html><head><title>Rerun</title></head><body><script src="re_viewer.js"></script></body></html>'
    out = quiet_index(page)
    assert out.index(QUIET) < out.index("</head>") < out.index("re_viewer.js")
    assert "console[name] = () => {}" in QUIET and 'get("log")' in QUIET


def test_index_without_head_is_refused() -> None:
    with pytest.raises(ViewerAssetsError, match="no </head>"):
        quiet_index("<html><body></body></html>")
