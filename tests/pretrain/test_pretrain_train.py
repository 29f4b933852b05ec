"""Pretraining loop: resume equals an uninterrupted run; two gloo processes equal one process; outputs."""

import json
import shutil
import socket

import pytest
import torch
import torch.multiprocessing as mp

from tsnav.checkpoint import load_tensors
from tsnav.pretrain.synthetic import write_synthetic_dataset
from tsnav.pretrain.train import PretrainConfig, read_progress, train
from tsnav.schedule import warmup_cosine as lr_at


pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = dict(model="vit_micro", patch_size=8, img_size=16, log_every=1, viz_images=0)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("synth"), size=16)


def weights(run):
    return load_tensors(run / "model.safetensors")[0]


def test_lr_schedule_by_hand():
    assert lr_at(0, 10, 1.0, 2) == 0.5 and lr_at(1, 10, 1.0, 2) == 1.0
    assert lr_at(2, 10, 1.0, 2) == pytest.approx(1.0)
    assert lr_at(6, 10, 1.0, 2, 0.0) == pytest.approx(0.5)  # half-way through the cosine
    assert lr_at(10, 10, 1.0, 2, 0.1) == pytest.approx(0.1) and lr_at(50, 10, 1.0, 2, 0.1) == pytest.approx(0.1)


@pytest.mark.parametrize("method", ["demae", "demae-crop"])
def test_resume_reproduces_uninterrupted_run(data, tmp_path, method):
    cfg = PretrainConfig(method=method, batch_size=4, steps=4, checkpoint_every=100, **TINY)
    a = train(cfg, data, tmp_path / "a", progress=False)
    part = train(cfg, data, tmp_path / "b", stop_at=2, progress=False)
    assert part["finished"] is False and part["step"] == 2
    assert read_progress(tmp_path / "b")["step"] == 2
    assert not (tmp_path / "b" / "encoder.safetensors").exists()
    b = train(cfg, data, tmp_path / "b", progress=False)
    assert a["finished"] and b["finished"] and b["step"] == 4
    wa, wb = weights(tmp_path / "a"), weights(tmp_path / "b")
    assert wa.keys() == wb.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    # the weights moved, and a finished run is not retrained
    m0 = (tmp_path / "a" / "model.safetensors").stat().st_mtime_ns
    assert train(cfg, data, tmp_path / "a", progress=False)["finished"]
    assert (tmp_path / "a" / "model.safetensors").stat().st_mtime_ns == m0


def test_truncated_newest_checkpoint_resumes_from_the_previous_one(data, tmp_path, capsys):
    """Issue 16 section 5: the newest two checkpoints are kept; a broken newest one is named in one line and
    the run resumes from the one before, ending exactly like an uninterrupted run."""
    cfg = PretrainConfig(method="mae", batch_size=4, steps=6, checkpoint_every=2, **TINY)
    train(cfg, data, tmp_path / "a", progress=False)
    train(cfg, data, tmp_path / "b", stop_at=5, progress=False)
    assert read_progress(tmp_path / "b")["step"] == 5
    ckpts = tmp_path / "b" / "checkpoints"
    assert sorted(p.name for p in ckpts.iterdir()) == ["ckpt_000000004", "ckpt_000000005"]
    assert sorted(p.name for p in (ckpts / "ckpt_000000005").iterdir()) == [
        "model.safetensors",
        "optimizer.safetensors",
        "state.json",
    ]
    broken = ckpts / "ckpt_000000005" / "model.safetensors"
    broken.write_bytes(broken.read_bytes()[:64])
    capsys.readouterr()
    b = train(cfg, data, tmp_path / "b", progress=False)
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("tsnav:")]
    assert len(err) == 1 and str(broken) in err[0] and "resuming from ckpt_000000004" in err[0], err
    assert (ckpts / "ckpt_000000005.broken" / "model.safetensors").exists()  # kept, no longer listed
    assert b["finished"] and b["step"] == 6
    wa, wb = weights(tmp_path / "a"), weights(tmp_path / "b")
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k


def test_accumulation_equals_larger_batch(data, tmp_path):
    big = PretrainConfig(method="mae", batch_size=4, steps=2, **TINY)
    acc = PretrainConfig(method="mae", batch_size=2, accum_iter=2, steps=2, **TINY)
    train(big, data, tmp_path / "big", progress=False)
    train(acc, data, tmp_path / "acc", progress=False)
    wa, wb = weights(tmp_path / "big"), weights(tmp_path / "acc")
    assert not any(k.startswith("decoder_pred_depth") for k in wa)
    for k in wa:
        torch.testing.assert_close(wa[k], wb[k], atol=1e-5, rtol=1e-4)


def test_changed_config_is_refused_and_outputs_exist(data, tmp_path):
    cfg = PretrainConfig(method="demae", batch_size=4, steps=2, **{**TINY, "viz_images": 3})
    train(cfg, data, tmp_path / "r", progress=False)
    for f in ("config.json", "checkpoints", "model.safetensors", "encoder.safetensors", "recon.png"):
        assert (tmp_path / "r" / f).exists(), f
    enc, meta = load_tensors(tmp_path / "r" / "encoder.safetensors")
    assert meta["arch"] == "vit" and json.loads(meta["config"])["img_size"] == 16
    assert not any(k.startswith(("decoder", "mask_token")) for k in enc)
    assert list((tmp_path / "r" / "tb").iterdir())
    other = PretrainConfig(method="demae", batch_size=2, steps=2, **TINY)
    with pytest.raises(ValueError, match="batch_size"):
        train(other, data, tmp_path / "r", progress=False)
    with pytest.raises(ValueError, match="fewer than one global batch"):
        train(PretrainConfig(method="demae", batch_size=1000, steps=1, **TINY), data, tmp_path / "x", progress=False)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _replica_worker(rank, world, port, data, out):
    import os

    import torch.distributed as dist
    from safetensors.torch import save_file

    torch.set_num_threads(1)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    from tsnav.pretrain.train import PretrainConfig, train_model

    cfg = PretrainConfig(method="demae", batch_size=2, steps=3, **TINY)
    _, model = train_model(cfg, data, out / "run", progress=False)
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(out / f"replica{rank}.safetensors"))
    dist.destroy_process_group()


def test_two_gloo_processes_keep_replicas_identical_and_match_one_process(data, tmp_path):
    mp.spawn(_replica_worker, args=(2, _free_port(), data, tmp_path), nprocs=2, join=True)
    r0 = load_tensors(tmp_path / "replica0.safetensors")[0]
    r1 = load_tensors(tmp_path / "replica1.safetensors")[0]
    for k in r0:
        assert torch.equal(r0[k], r1[k]), k
    assert read_progress(tmp_path / "run")["world_size"] == 2
    # one process with the same global batch (2 x 2) learns the same weights up to float reordering
    single = PretrainConfig(method="demae", batch_size=4, steps=3, **TINY)
    train(single, data, tmp_path / "single", progress=False)
    w = weights(tmp_path / "single")
    for k in r0:
        torch.testing.assert_close(r0[k], w[k], atol=2e-5, rtol=1e-4)
    init = load_tensors(tmp_path / "run" / "model.safetensors")[0]
    assert torch.equal(init["blocks.0.attn.qkv.weight"], r0["blocks.0.attn.qkv.weight"])


def test_interrupt_writes_a_checkpoint_and_resume_matches(data, tmp_path, monkeypatch):
    import tsnav.pretrain.train as tr

    cfg = PretrainConfig(method="demae", batch_size=4, steps=4, checkpoint_every=100, **TINY)
    train(cfg, data, tmp_path / "a", progress=False)
    calls = {"n": 0}
    real = tr.compute_loss

    def flaky(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:  # Ctrl-C / SIGTERM during step 3
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(tr, "compute_loss", flaky)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, data, tmp_path / "b", progress=False)
    assert read_progress(tmp_path / "b")["step"] == 2
    monkeypatch.setattr(tr, "compute_loss", real)
    train(cfg, data, tmp_path / "b", progress=False)
    wa, wb = weights(tmp_path / "a"), weights(tmp_path / "b")
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k


def test_sigterm_stops_cleanly_at_a_step_boundary(data, tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    code = (
        "import sys\n"
        "from tsnav.pretrain.train import PretrainConfig, train\n"
        "cfg = PretrainConfig(method='demae', batch_size=4, steps=100000, checkpoint_every=10**9, "
        "model='vit_micro', patch_size=8, img_size=16, log_every=1, viz_images=0)\n"
        "try:\n"
        "    train(cfg, sys.argv[1], sys.argv[2], progress=False)\n"
        "except KeyboardInterrupt:\n"
        "    sys.exit(130)\n"
    )
    p = subprocess.Popen(
        [sys.executable, "-c", code, str(data), str(tmp_path / "r")], env={**os.environ, "OMP_NUM_THREADS": "1"}
    )
    deadline = time.time() + 120
    while not list((tmp_path / "r" / "tb").glob("events*")) and time.time() < deadline:
        time.sleep(0.2)
    time.sleep(1.0)
    p.send_signal(signal.SIGTERM)
    assert p.wait(timeout=120) == 130
    prog = read_progress(tmp_path / "r")
    assert prog["step"] >= 1 and not prog["finished"]
    ck = tmp_path / "r" / "checkpoints" / f"ckpt_{prog['step']:09d}"
    assert (ck / "model.safetensors").exists() and (ck / "optimizer.safetensors").exists()


def _to_legacy_layout(run, steps):
    """Rewrite a run folder's checkpoints by hand into the layout before ``checkpoints/``: progress.json naming
    ckpt-<step 8 digits>-model/optim.safetensors files, the checkpoint before under ``previous``."""
    records = []
    for step in steps:
        ck = run / "checkpoints" / f"ckpt_{step:09d}"
        rec = json.loads((ck / "state.json").read_text())
        tag = f"ckpt-{step:08d}"
        (ck / "model.safetensors").rename(run / f"{tag}-model.safetensors")
        (ck / "optimizer.safetensors").rename(run / f"{tag}-optim.safetensors")
        records.append(rec | {"model_file": f"{tag}-model.safetensors", "optim_file": f"{tag}-optim.safetensors"})
    shutil.rmtree(run / "checkpoints")
    (run / "progress.json").write_text(json.dumps(records[1] | {"previous": records[0]}))


def test_legacy_run_folder_resumes_and_continues_in_the_one_layout(data, tmp_path, capsys):
    """A run folder written before the one checkpoint layout (progress.json + ckpt-* files) is still read and
    resumed, also from its ``previous`` record when the newest file is broken; new checkpoints go to
    checkpoints/."""
    cfg = PretrainConfig(method="mae", batch_size=4, steps=6, checkpoint_every=2, **TINY)
    train(cfg, data, tmp_path / "a", progress=False)
    for name, broken in (("b", False), ("c", True)):
        run = tmp_path / name
        train(cfg, data, run, stop_at=5, progress=False)
        _to_legacy_layout(run, [4, 5])
        assert read_progress(run)["step"] == 5 and read_progress(run)["model_file"] == "ckpt-00000005-model.safetensors"
        if broken:
            f = run / "ckpt-00000005-model.safetensors"
            f.write_bytes(f.read_bytes()[:64])
        capsys.readouterr()
        res = train(cfg, data, run, progress=False)
        err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("tsnav:")]
        assert len(err) == int(broken) and (not broken or "step 4" in err[0]), err
        assert res["finished"] and res["step"] == 6
        assert [p.name for p in (run / "checkpoints").iterdir()] == ["ckpt_000000006"]
        assert read_progress(run)["step"] == 6 and read_progress(run)["finished"]
        wa, wb = weights(tmp_path / "a"), weights(run)
        for k in wa:
            assert torch.equal(wa[k], wb[k]), (name, k)
