"""Test helper for the rl tests: re-running a recorded rollout through a model."""

from __future__ import annotations

import json

import torch

from tsnav.agent.model import ActorCritic
from tsnav.agent.observe import Observer
from tsnav.rl.rollout import Rollout


def replay(model: ActorCritic, observer: Observer, ro: Rollout) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Re-run a recorded rollout's observations and actions through ``model``: ``(logp, entropy, value)``
    ``(T, B)`` with gradients (same recurrent-state resets; dropout as set by the model's mode)."""
    dev = next(model.parameters()).device
    state = ro.start
    logps, ents, values = [], [], []
    for t in range(ro.states.shape[0]):
        logits, v, state = model(observer(ro.states[t], ro.targets[t]), state)
        dist = torch.distributions.Categorical(logits=logits)
        a = torch.from_numpy(ro.actions[t]).to(dev)
        logps.append(dist.log_prob(a))
        ents.append(dist.entropy())
        values.append(v)
        state = state.with_action(a).reset(ro.finished[t])
    return torch.stack(logps), torch.stack(ents), torch.stack(values)


class RecordingTrainer:
    """Base of the experiment and demo tests' trainers: records each call's (reward, features, C_target, seed)
    in ``calls`` and its detection table in ``detections``; subclasses train in ``train``."""

    def __init__(self):
        self.calls = []
        self.detections = []

    def __call__(self, tc, agent, run_dir):
        self.calls.append((tc.reward, tc.features, tc.c_target, tc.seed))
        self.detections.append(tc.detections)
        return self.train(tc, agent, run_dir)

    def train(self, tc, agent, run_dir):
        raise NotImplementedError


def train_argv(data, out, features: str, *extra: str) -> list[str]:
    """``tsnav train`` arguments of the tests' small batched runs: ``data`` and its feature cache ``features``, the
    oracle's detection tables, 4 episodes of the ``cpu`` preset in 5-step rollouts into ``out``, quiet; ``extra``
    adds or sets the rest (``"--updates", "4"``, ...)."""
    return [
        "train",
        "--data",
        str(data),
        "--features",
        features,
        "--detections",
        "oracle",
        "--algo",
        "batched",
        "--out",
        str(out),
        "--num-envs",
        "4",
        "--preset",
        "cpu",
        "--rollout-steps",
        "5",
        *extra,
        "--quiet",
    ]


class StandInTrainer(RecordingTrainer):
    """Writes a loadable run folder (config.json, one checkpoint of an untrained agent, a short log)."""

    def train(self, tc, agent, run_dir):
        from tsnav.rl.checkpoint import save_checkpoint
        from tsnav.rl.assemble import load_bank, make_model, make_observer

        run_dir.mkdir(parents=True, exist_ok=True)
        bank, det = load_bank(tc)
        model = make_model(agent, make_observer(bank, tc, det_features=det), tc.seed)
        with torch.no_grad():  # mostly turn on the spot, so that some episodes see their target
            model.actor.bias.copy_(torch.tensor([1.0, 0.0, 4.0, 0.0, 0.0, -2.0]))
        (run_dir / "config.json").write_text(
            json.dumps({"format": "tsnav-train-run", "train": tc.to_dict(), "agent": agent.__dict__})
        )
        with open(run_dir / "log.jsonl", "w") as f:
            for u in range(1, 4):
                f.write(
                    json.dumps({"update": u, "env_steps": 100 * u, "return": 0.1 * u + tc.seed, "SR": 0.1 * u}) + "\n"
                )
        save_checkpoint(
            run_dir, {"update": 3, "env_steps": 300, "episodes": 10, "seconds": 1.0, "finished": True}, model
        )
