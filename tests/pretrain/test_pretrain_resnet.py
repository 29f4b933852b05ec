"""ResNet18 baseline: torchvision layout and numbers, weight loading, supervised pretraining on the world."""

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from tsnav.pretrain.resnet import ResNet18, load_resnet_weights
from tsnav.pretrain.synthetic import write_synthetic_dataset
from tsnav.pretrain.train import PretrainConfig, train
from script_helpers import load_script


pytestmark = pytest.mark.usefixtures("one_torch_thread")

FIX = Path(__file__).resolve().parents[1] / "fixtures" / "pretrain"


def _formula():
    return load_script(FIX / "make_resnet_fixture.py").formula_state


def test_torchvision_layout_and_features(tmp_path):
    shapes = json.loads((FIX / "resnet_keys.json").read_text())
    ours = ResNet18(num_classes=22)
    own = {k: list(v.shape) for k, v in ours.state_dict().items()}
    assert {k: v for k, v in own.items() if not k.startswith("fc.")} == {
        k: v for k, v in shapes.items() if not k.startswith("fc.")
    }
    save_file(_formula()(shapes), str(tmp_path / "tv.safetensors"))
    info = load_resnet_weights(ours, tmp_path / "tv.safetensors")
    assert info["ignored"] == ["fc.bias", "fc.weight"]  # ImageNet head does not fit 22 outputs
    io = load_file(str(FIX / "resnet_io.safetensors"))
    with torch.no_grad():
        y = ours.eval().feature_map(io["x"])
    torch.testing.assert_close(y, io["y"], atol=1e-4, rtol=1e-4)


def test_bad_weights_are_named(tmp_path):
    save_file({"conv1.weight": torch.zeros(64, 3, 7, 7)}, str(tmp_path / "w.safetensors"))
    with pytest.raises(ValueError, match="missing keys: bn1.bias"):
        load_resnet_weights(ResNet18(), tmp_path / "w.safetensors")


def test_supervised_pretraining_lowers_the_loss(tmp_path):
    root = write_synthetic_dataset(tmp_path / "d", size=32)
    cfg = PretrainConfig(
        method="resnet18-sup", img_size=32, batch_size=8, steps=4, base_lr=0.02, log_every=1, warmup_fraction=0.1
    )
    res = train(cfg, root, tmp_path / "run", progress=False)
    assert res["finished"]
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ea = EventAccumulator(str(tmp_path / "run" / "tb"))
    ea.Reload()
    bce = [e.value for e in ea.Scalars("losses/bce")]
    assert len(bce) == 4 and min(bce[-2:]) < bce[0]
    from tsnav.pretrain.features import load_encoder

    enc = load_encoder(str(tmp_path / "run"), img_size=32)
    assert enc.arch == "resnet18" and enc.method == "resnet18-sup"
    assert enc.encode(torch.zeros(1, 3, 32, 32)).shape == (1, 512, 1, 1)
