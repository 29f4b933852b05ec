"""tsnav analyze plot-selection: a run's milestones on one or two validation sets, read from selection.json files; the chosen
milestone and the episode counts come from the files; bad input is refused in one line and nothing is written."""

import json

from script_helpers import load_analysis


def _selection(path, srs, best, episodes):
    scores = {
        f"ckpt_{u:09d}": {"update": u, "metrics": {"ALL": {"SR": sr, "SPL": sr / 2, "episodes": episodes}}}
        for u, sr in srs.items()
    }
    path.write_text(json.dumps({"best": best, "scores": scores}))
    return path


def test_reads_the_files_and_writes_a_png(tmp_path, capsys):
    mod = load_analysis("plot_selection")
    small = _selection(tmp_path / "a.json", {500: 0.8, 250: 0.7, 750: 0.75}, "ckpt_000000500", 400)
    large = _selection(tmp_path / "b.json", {250: 0.72, 500: 0.78, 750: 0.79}, "ckpt_000000750", 2000)
    updates, sr, spl, best, n = mod.read_selection(str(small))
    assert updates == [250, 500, 750] and sr == [70.0, 80.0, 75.0] and spl == [35.0, 40.0, 37.5]
    assert best == 500 and n == 400
    out = tmp_path / "sel.png"
    assert mod.main(["--out", str(out), "--run", f"seed 0={small},{large}"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    one = tmp_path / "one.png"  # one list per run: the milestones on the scoring episodes alone
    assert mod.main(["--out", str(one), "--episodes", "train", "--run", f"a={small}", "--run", f"b={large}"]) == 0
    assert one.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_input_is_one_line(tmp_path, capsys):
    mod = load_analysis("plot_selection")
    good = _selection(tmp_path / "a.json", {250: 0.7}, "ckpt_000000250", 400)
    bad = tmp_path / "bad.json"
    bad.write_text('{"best": "x"}')
    running = _selection(tmp_path / "running.json", {250: 0.7}, None, 400)  # a selection still running
    out = tmp_path / "sel.png"
    for run in (
        f"seed 0={good},{good},{good}",
        "seed 0=",
        f"seed 0={good},{bad}",
        f"seed 0={good},{tmp_path / 'missing.json'}",
        f"seed 0={good},{running}",
    ):
        assert mod.main(["--out", str(out), "--run", run]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("plot_selection: error:") and len(err.splitlines()) == 1
    assert not out.exists()
