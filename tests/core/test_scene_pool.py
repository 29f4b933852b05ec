"""Per-scene work over processes (:mod:`tsnav.scene_pool`): the feature caches and detection tables written by two
worker processes are the same bytes as those of the one-thread loop in this process (the reference), and an error
in a worker reaches the caller."""

import os
import shutil
import time
from concurrent.futures.process import BrokenProcessPool

import h5py
import numpy as np
import pytest
import torch

from tsnav.data.reader import list_scenes
from tsnav.detect.learned import LearnedDetector
from tsnav.detect.model import DetectorConfig, GridDetector
from tsnav.pipeline.detector_steps import write_learned_tables
from tsnav.pretrain.features import cache_features, load_encoder
from tsnav.pretrain.model import vit_tiny
from tsnav.pretrain.synthetic import write_synthetic_dataset
from tsnav.pretrain.train import save_encoder
from tsnav.scene_pool import as_is, map_scenes

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _square(ctx, x):
    return ctx * x * x


def _fail_on_three(ctx, x):
    if x == 3:
        raise ValueError("item three")
    return x


def _fail_or_sleep(ctx, x):
    if x == 0:
        time.sleep(1.0)
        raise ValueError("first item")
    time.sleep(600)
    return x


def _die_on_two(ctx, x):
    if x == 2:
        os._exit(3)
    return x


def _datasets(path):
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in sorted(f.keys())}


def test_map_scenes_in_process_and_in_workers():
    want = {i: 10 * x * x for i, x in enumerate(range(6))}
    torch.set_num_threads(3)
    try:
        assert dict(map_scenes(_square, range(6), as_is, 10, workers=1)) == want
        assert torch.get_num_threads() == 3  # the caller's count is restored after the in-process loop
    finally:
        torch.set_num_threads(1)
    assert dict(map_scenes(_square, range(6), as_is, 10, workers=2)) == want
    with pytest.raises(ValueError, match="item three"):
        list(map_scenes(_fail_on_three, range(6), as_is, None, workers=2))
    with pytest.raises(BrokenProcessPool):  # a worker that dies outright stops the pool instead of hanging it
        list(map_scenes(_die_on_two, range(4), as_is, None, workers=2))


def test_an_error_stops_the_other_workers():
    """A worker's error terminates the others (SIGTERM) instead of waiting for their items: the 600 s item is cut."""
    t = time.monotonic()
    with pytest.raises(ValueError, match="first item"):
        list(map_scenes(_fail_or_sleep, range(2), as_is, None, workers=2))
    assert time.monotonic() - t < 300


def test_default_workers_follow_the_cores_with_a_cap(monkeypatch):
    import tsnav.scene_pool as sp

    monkeypatch.setattr(sp.os, "sched_getaffinity", lambda pid: set(range(64)))
    assert sp.default_workers() == sp.MAX_DEFAULT_WORKERS
    monkeypatch.setattr(sp.os, "sched_getaffinity", lambda pid: {0, 1})
    assert sp.default_workers() == 2


def test_features_from_two_workers_equal_the_one_thread_loop(tmp_path):
    torch.manual_seed(5)
    save_encoder(vit_tiny(patch_size=8, img_size=16), tmp_path / "enc.safetensors", "demae")
    enc = load_encoder(str(tmp_path / "enc.safetensors"))
    roots = {}
    for workers in (0, 2):
        roots[workers] = write_synthetic_dataset(tmp_path / f"data{workers}", size=16)
        files = cache_features(enc, roots[workers], "t", batch_size=5, progress=False, workers=workers)
        assert len(files) == 3
    for a, b in zip(list_scenes(roots[0]), list_scenes(roots[2])):
        da, db = _datasets(a / "features_t.hdf5"), _datasets(b / "features_t.hdf5")
        assert da.keys() == db.keys()
        for k in da:
            np.testing.assert_array_equal(da[k], db[k])


def test_tables_from_two_workers_equal_the_one_thread_loop(tiny_world, tmp_path):
    torch.manual_seed(2)
    scene = list_scenes(tiny_world)[0]
    from tsnav.data.reader import load_scene

    size = load_scene(scene).image_size
    det = LearnedDetector(GridDetector(DetectorConfig(image_size=size)).eval(), temperature=1.0)
    roots = {}
    for workers in (1, 2):
        roots[workers] = tmp_path / f"w{workers}"
        shutil.copytree(tiny_world, roots[workers], ignore=shutil.ignore_patterns("detections_*", "features_*"))
        out = write_learned_tables(roots[workers], "learned", det, progress=False, say=lambda m: None, workers=workers)
        assert out["written"] == len(list_scenes(tiny_world))
    for a, b in zip(list_scenes(roots[1]), list_scenes(roots[2])):
        da, db = _datasets(a / "detections_learned.hdf5"), _datasets(b / "detections_learned.hdf5")
        assert da.keys() == db.keys() and da
        for k in da:
            np.testing.assert_array_equal(da[k], db[k])


def test_features_command_takes_workers(tmp_path, capsys):
    from tsnav.cli import main

    root = write_synthetic_dataset(tmp_path / "data", size=16)
    torch.manual_seed(1)
    save_encoder(vit_tiny(patch_size=8, img_size=16), tmp_path / "enc.safetensors", "demae")
    assert (
        main(["features", "--encoder", str(tmp_path / "enc.safetensors"), "--data", str(root), "--workers", "-1"]) == 2
    )
    assert "--workers must be >= 0" in capsys.readouterr().err
    assert (
        main(
            [
                "features",
                "--encoder",
                str(tmp_path / "enc.safetensors"),
                "--data",
                str(root),
                "--name",
                "w",
                "--workers",
                "2",
                "--quiet",
            ]
        )
        == 0
    )
    assert "features_w.hdf5 in 3 scenes" in capsys.readouterr().out
    assert all((p / "features_w.hdf5").exists() for p in list_scenes(root))


def test_workers_start_from_a_script_on_standard_input(tmp_path):
    """A script piped to ``python -`` (as shell scripts run their Python steps) has
    ``__main__.__file__ == '<stdin>'``; spawned workers used to die re-running that path (BrokenProcessPool). The
    scene pool and the world's builders start from such a script (``distributed.spawn_context()`` at every spawn
    site: these two, the ranks, the experiment's job pool, the A3C workers, the demo's table writer)."""
    import subprocess
    import sys

    script = (
        "import operator\n"
        "from tsnav.scene_pool import as_is, map_scenes\n"
        "print(sorted(map_scenes(operator.mul, range(5), as_is, 3, workers=2)))\n"
        "import __main__; print(__main__.__file__)\n"  # restored after the pool started
        "from tsnav.world.build import build_dataset\n"  # the world's pool of builders, the other spawn site
        "print(len(build_dataset('world', 'tiny', workers=2, progress=False)))\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    r = subprocess.run(
        [sys.executable, "-"], input=script, capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split("\n")[:3] == ["[(0, 0), (1, 3), (2, 6), (3, 9), (4, 12)]", "<stdin>", "5"]


def test_spawnable_main_hides_only_a_main_file_that_is_not_there(tmp_path, monkeypatch):
    import sys
    import types

    from tsnav.distributed import spawnable_main

    for path, hidden in (("<stdin>", True), (str(tmp_path / "gone.py"), True), (__file__, False)):
        main = types.ModuleType("__main__")
        main.__file__, main.__spec__ = path, None
        monkeypatch.setitem(sys.modules, "__main__", main)
        with spawnable_main():
            assert hasattr(main, "__file__") != hidden, path
        assert main.__file__ == path
    main = types.ModuleType("__main__")  # python -c: no file at all
    main.__spec__ = None
    monkeypatch.setitem(sys.modules, "__main__", main)
    with spawnable_main():
        assert not hasattr(main, "__file__")


def test_spawn_context_starts_children_of_a_main_that_is_not_on_disk(monkeypatch):
    """``distributed.spawn_context()`` (the context of every tsnav spawn site) starts a child where the plain
    ``spawn`` context's child dies re-running the parent's missing main file."""
    import multiprocessing
    import sys
    import time
    import types

    from tsnav.distributed import spawn_context

    main = types.ModuleType("__main__")
    main.__file__, main.__spec__ = "<stdin>", None
    monkeypatch.setitem(sys.modules, "__main__", main)
    codes = {}
    for name, ctx in (("plain", multiprocessing.get_context("spawn")), ("tsnav", spawn_context())):
        p = ctx.Process(target=time.sleep, args=(0,))
        p.start()
        p.join(120)
        codes[name] = p.exitcode
        assert main.__file__ == "<stdin>"
    assert codes["plain"] != 0 and codes["tsnav"] == 0, codes


def test_trim_memory_hands_freed_heap_back():
    """Freed arrays that glibc keeps on its heap (after a large free raised its mmap threshold) stay in the RSS
    until ``distributed.trim_memory``, as the experiment's parent kept 11 GB after pretraining. In a fresh
    interpreter, so that the allocator's state is known."""
    import subprocess
    import sys

    script = (
        "import numpy as np\n"
        "from tsnav.distributed import trim_memory\n"
        "rss = lambda: int(open('/proc/self/statm').read().split()[1]) * 4096\n"
        "big = np.ones(16 << 20, np.uint8); del big\n"
        "parts, pins = [], []\n"
        "for _ in range(300):\n"
        "    parts.append(np.ones(1 << 20, np.uint8)); pins.append(np.ones(64, np.uint8))\n"
        "del parts\n"
        "before = rss(); trimmed = trim_memory(); after = rss()\n"
        "print(trimmed, before - after)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    trimmed, freed = r.stdout.split()
    if trimmed != "True":
        pytest.skip("no glibc malloc_trim here")
    assert int(freed) > 200 << 20, freed  # about 300 MB of the freed 1 MB arrays go back
