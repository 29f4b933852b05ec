"""Atomic writes: the new content appears whole, and a failed write leaves the previous file as it was."""

import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PIL import Image

from tsnav.atomic import atomic_save_figure, atomic_write_text


def _figure():
    fig = Figure(figsize=(2, 1))
    FigureCanvasAgg(fig)
    fig.add_subplot(111).plot([0, 1], [1, 0])
    return fig


def test_figure_written_whole_and_failed_write_keeps_the_old_one(tmp_path):
    path = tmp_path / "sub" / "curve.png"
    assert atomic_save_figure(_figure(), path, dpi=50) == path
    with Image.open(path) as im:
        assert im.format == "PNG" and im.size == (100, 50)
    before = path.read_bytes()
    broken = _figure()

    def half_then_fail(buf, **kw):  # a render that dies midway, after writing part of the picture
        buf.write(before[:20])
        raise RuntimeError("renderer died")

    broken.savefig = half_then_fail
    with pytest.raises(RuntimeError, match="renderer died"):
        atomic_save_figure(broken, path, dpi=50)
    assert path.read_bytes() == before
    assert sorted(p.name for p in path.parent.iterdir()) == ["curve.png"]  # no temp file left behind


def test_text_write_replaces_content(tmp_path):
    path = tmp_path / "a.txt"
    atomic_write_text(path, "one")
    atomic_write_text(path, "two")
    assert path.read_text() == "two"


def test_written_files_have_the_mode_open_would_give(tmp_path):
    import os
    import stat

    from tsnav.atomic import atomic_path, atomic_write_text, file_mode

    old = os.umask(0o022)
    try:
        assert file_mode() == 0o644
        atomic_write_text(tmp_path / "a.json", "{}")
        with atomic_path(tmp_path / "b.bin") as tmp:
            tmp.write_bytes(b"x")
        for name in ("a.json", "b.bin"):
            assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o644  # not mkstemp's 0o600
        os.chmod(tmp_path / "a.json", 0o640)  # a file replaced keeps its own mode, as open() would
        atomic_write_text(tmp_path / "a.json", "[]")
        assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) == 0o640
    finally:
        os.umask(old)
