"""Linear probes of a frozen encoder: what do its features say about depth and about visible objects?

Used to compare DE-MAE, MAE, the ResNet18 baseline and an untrained encoder (paper §III-C / Table III
asks whether depth pretraining gives the agent spatial perception; this answers it without RL).

* Depth: per feature-grid cell, a ridge regression from the cell's C-vector to the mean true depth of the
  image region under the cell (metres). Reported as RMSE in metres on the evaluation split, beside the RMSE
  of predicting the fit split's mean depth.
* Objects: per image, an L2-regularised logistic regression from the mean-pooled feature to the 22 "target
  category visible" labels (``Scene.pixels >= min pixels``). Reported as mean average precision over the
  categories that have positives and negatives in the evaluation split, beside the chance level (mean
  prevalence).

Probes are fit on the ``fit_split`` (train) images and evaluated on ``eval_split`` (val) images. With few
train scenes a linear depth map learnt on them may not transfer to a new room at all, so the depth probe is
also reported *within* the evaluation split (``depth_rmse_heldout_m``): fit on the first half of each
scene's states (sorted keys, i.e. positions of smaller x) and scored on the second half.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .data import RGBDImages, normalize_rgb
from .features import Encoder, load_encoder


@dataclass
class ProbeConfig:
    """Settings of :func:`probe_encoder`."""

    fit_split: str = "train"
    """Split whose images fit the probes."""
    eval_split: str = "val"
    """Split whose images score them."""
    max_images: int = 2000
    """At most this many images per split (an even spread over the split)."""
    ridge: float = 1.0
    """L2 penalty of the depth ridge regression (on standardised features)."""
    logistic_l2: float = 1e-3
    """L2 penalty (per image, mean loss) of the category logistic regression."""
    lbfgs_iters: int = 100
    """L-BFGS iterations of the logistic regression."""
    batch_size: int = 64
    """Images per encoder call."""


def average_precision(scores: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Per-column average precision of ``scores [N, K]`` for binary ``labels [N, K]`` (NaN without positives).

    AP = mean over positives of the precision at that positive's rank (ties broken by order), as
    scikit-learn's ``average_precision_score`` without interpolation.
    """
    order = np.argsort(-scores, axis=0, kind="stable")
    lab = np.take_along_axis(labels.astype(np.float64), order, axis=0)  # [N, K] sorted by score
    tp = np.cumsum(lab, axis=0)
    precision = tp / np.arange(1, len(lab) + 1)[:, None]
    npos = lab.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(npos > 0, (precision * lab).sum(0) / npos, np.nan)


def ridge_fit(x: np.ndarray, y: np.ndarray, lam: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ridge regression on standardised ``x [N, C]`` to ``y [N]``: returns (mean, std, weights [C+1])."""
    mu, sd = x.mean(0), x.std(0) + 1e-6
    z = np.concatenate([(x - mu) / sd, np.ones((len(x), 1))], axis=1).astype(np.float64)
    reg = lam * np.eye(z.shape[1])
    reg[-1, -1] = 0.0  # no penalty on the bias
    w = np.linalg.solve(z.T @ z + reg, z.T @ y.astype(np.float64))
    return mu, sd, w


def ridge_predict(x: np.ndarray, model) -> np.ndarray:
    mu, sd, w = model
    return ((x - mu) / sd) @ w[:-1] + w[-1]


def logistic_fit(x: np.ndarray, y: np.ndarray, l2: float, iters: int) -> tuple:
    """Multi-label logistic regression on standardised ``x [N, C]``, ``y [N, K]``: (mean, std, W, b)."""
    mu, sd = x.mean(0), x.std(0) + 1e-6
    z = torch.from_numpy(((x - mu) / sd).astype(np.float32))
    t = torch.from_numpy(y.astype(np.float32))
    w = torch.zeros(z.shape[1], t.shape[1], requires_grad=True)
    b = torch.zeros(t.shape[1], requires_grad=True)
    opt = torch.optim.LBFGS([w, b], max_iter=iters, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = F.binary_cross_entropy_with_logits(z @ w + b, t) + l2 * (w**2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return mu, sd, w.detach().numpy(), b.detach().numpy()


def logistic_scores(x: np.ndarray, model) -> np.ndarray:
    mu, sd, w, b = model
    return ((x - mu) / sd) @ w + b


def _spread(n: int, k: int) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, num=min(n, k)).round().astype(np.int64))


@torch.no_grad()
def encode_split(encoder: Encoder, images: RGBDImages, index: np.ndarray, batch_size: int = 64):
    """Features and targets of ``images[index]``: cell features ``[N*h*w, C]``, cell mean depth ``[N*h*w]``
    (metres), pooled features ``[N, C]`` and labels ``[N, 22]``."""
    cells, depth, pooled, labels = [], [], [], []
    for a in range(0, len(index), batch_size):
        b = images.get(index[a : a + batch_size])
        f = encoder.encode(normalize_rgb(b["rgb"]).to(encoder.device)).float().cpu()  # [B, C, h, w]
        h, w = f.shape[-2:]
        d = F.adaptive_avg_pool2d(b["depth"], (h, w))  # [B, 1, h, w] mean metres under each cell
        cells.append(f.permute(0, 2, 3, 1).reshape(-1, f.shape[1]).numpy())
        depth.append(d.reshape(-1).numpy())
        pooled.append(f.mean((2, 3)).numpy())
        labels.append(b["labels"].numpy())
    return np.concatenate(cells), np.concatenate(depth), np.concatenate(pooled), np.concatenate(labels)


def probe_encoder(encoder: Encoder, root, config: ProbeConfig | None = None) -> dict:
    """Fit and score both probes; returns a JSON-able dict::

    depth_rmse_m, depth_rmse_baseline_m, depth_rmse_heldout_m, depth_rmse_heldout_baseline_m,
    map, map_chance, categories, n_fit, n_eval, config
    """
    cfg = config or ProbeConfig()
    fit = RGBDImages(root, cfg.fit_split, encoder.img_size, labels=True)
    ev = RGBDImages(root, cfg.eval_split, encoder.img_size, labels=True)
    fi, ei = _spread(len(fit), cfg.max_images), _spread(len(ev), cfg.max_images)
    xc, yd, xp, yl = encode_split(encoder, fit, fi, cfg.batch_size)
    exc, eyd, exp, eyl = encode_split(encoder, ev, ei, cfg.batch_size)
    dm = ridge_fit(xc, yd, cfg.ridge)
    rmse = float(np.sqrt(np.mean((ridge_predict(exc, dm) - eyd) ** 2)))
    base = float(np.sqrt(np.mean((yd.mean() - eyd) ** 2)))
    # held-out positions within the evaluation split: first half of each scene's states -> second half
    si, row = ev.locate(ei)
    first = row < (ev.offsets[si + 1] - ev.offsets[si]) // 2
    cells = exc.shape[0] // len(ei)
    first_c = np.repeat(first, cells)
    hm = ridge_fit(exc[first_c], eyd[first_c], cfg.ridge)
    held = float(np.sqrt(np.mean((ridge_predict(exc[~first_c], hm) - eyd[~first_c]) ** 2)))
    held_base = float(np.sqrt(np.mean((eyd[first_c].mean() - eyd[~first_c]) ** 2)))
    keep = (yl.sum(0) > 0) & (yl.sum(0) < len(yl))  # categories the fit split can teach
    ev_ok = keep & (eyl.sum(0) > 0) & (eyl.sum(0) < len(eyl))
    m_ap = chance = float("nan")
    if ev_ok.any():
        lm = logistic_fit(xp, yl[:, keep], cfg.logistic_l2, cfg.lbfgs_iters)
        scores = np.zeros_like(eyl)
        scores[:, keep] = logistic_scores(exp, lm)
        ap = average_precision(scores[:, ev_ok], eyl[:, ev_ok])
        m_ap, chance = float(np.mean(ap)), float(eyl[:, ev_ok].mean())
    fit.close()
    ev.close()
    return {
        "encoder": encoder.spec,
        "method": encoder.method,
        "depth_rmse_m": rmse,
        "depth_rmse_baseline_m": base,
        "depth_rmse_heldout_m": held,
        "depth_rmse_heldout_baseline_m": held_base,
        "map": m_ap,
        "map_chance": chance,
        "categories": int(ev_ok.sum()),
        "n_fit": int(len(fi)),
        "n_eval": int(len(ei)),
        "config": asdict(cfg),
    }


def main(argv: list[str] | None = None) -> int:
    """``python -m tsnav.pretrain.probe --data ROOT --encoder SPEC [SPEC ...]``: print one JSON line each."""
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="python -m tsnav.pretrain.probe", description="linear probes of encoders"
    )
    ap.add_argument("--data", required=True)
    ap.add_argument("--encoder", nargs="+", required=True, help="encoder specs as for `tsnav features`")
    ap.add_argument("--model", default="vit_tiny")
    ap.add_argument("--patch", type=int, default=16)
    ap.add_argument("--img-size", type=int, default=64)
    ap.add_argument("--max-images", type=int, default=ProbeConfig.max_images)
    args = ap.parse_args(argv)
    for spec in args.encoder:
        enc = load_encoder(spec, args.model, args.patch, args.img_size)
        res = probe_encoder(enc, args.data, ProbeConfig(max_images=args.max_images))
        res.pop("config")
        print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
