"""Training configuration of the actor-critic trainers (paper III-D, IV-A; lineage A3C settings)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import ClassVar

from ..agent.model import PRESETS
from ..constants import C_TARGET
from ..errors import from_fields
from ..protocol import DEFAULT_PROTOCOL, PROTOCOLS, check_protocol
from ..schedule import linear_decay, warmup_cosine
from ..tsrm.reward import VARIANTS, RewardConfig

ALGOS = ("a3c", "batched")
#: Arithmetic of the network's forward passes while training: ``fp32``, or ``bf16`` (autocast: matrix products in
#: bfloat16, weights, optimizer and recurrent state in float32).
PRECISIONS = ("fp32", "bf16")
#: How the processes of a batched run share its updates (:attr:`TrainConfig.ranks`).
RANK_MODES = ("split", "staggered")
#: Learning-rate schedules of the agent's optimiser (:attr:`TrainConfig.lr_schedule`).
LR_SCHEDULES = ("constant", "linear", "cosine")
#: Fields that may change when a run is resumed (its budget); every other field must match the saved config.
BUDGET_FIELDS = ("episodes", "updates", "minutes")
#: Paper IV-A: the agent is trained for 1.5 M episodes.
PAPER_EPISODES = 1_500_000
#: Fields of :class:`~tsnav.tsrm.reward.RewardConfig` that :class:`TrainConfig` sets itself (``reward``,
#: ``distance_increase_scale``); its other fields (the paper's constants) are :attr:`TrainConfig.reward_settings`.
REWARD_OWN = ("variant", "distance_increase_scale")


def reward_settings_of(reward: RewardConfig) -> dict:
    """The fields of ``reward`` (its nested area too) that differ from the paper's constants, as
    :attr:`TrainConfig.reward_settings` holds them (canonical: equal rewards give equal dicts)."""
    return _nondefault(asdict(reward), asdict(RewardConfig()), skip=REWARD_OWN)


def _nondefault(now: dict, default: dict, skip=()) -> dict:
    out = {}
    for k, v in now.items():
        if k in skip:
            continue
        if isinstance(v, dict):
            sub = _nondefault(v, default.get(k, {}))
            if sub:
                out[k] = sub
        elif v != default.get(k):
            out[k] = v
    return out


@dataclass
class TrainConfig:
    """Everything a training run depends on besides the network sizes (:class:`~tsnav.agent.AgentConfig`)."""

    #: Allowed values of fields (the command-line options' choices, :mod:`tsnav.settings`).
    CHOICES: ClassVar[dict] = {
        "algo": ALGOS,
        "reward": VARIANTS,
        "preset": tuple(PRESETS),
        "ranks": RANK_MODES,
        "precision": PRECISIONS,
        "protocol": PROTOCOLS,
        "lr_schedule": LR_SCHEDULES,
    }

    data: str = ""
    """Dataset root (scene folders)."""
    features: str = ""
    """Name of the feature cache: files ``features_<name>.hdf5`` in every scene (``tsnav features``)."""
    detections: str | None = None
    """Name of the detection tables ``detections_<name>.hdf5`` (``tsnav detect``) driving the stage switch and
    the agent's target detections (``learned``, or ``oracle`` named explicitly). Required to train or evaluate:
    None is refused with a one-line error (no fallback to ground truth, issue 14)."""
    split: str = "train"
    """Scenes used for training."""
    algo: str = "a3c"
    """``a3c`` (the paper's asynchronous workers) or ``batched`` (synchronous A2C over many episodes)."""
    reward: str = "tsrm"
    """Reward variant of :class:`~tsnav.tsrm.reward.RewardConfig`: tsrm, baseline, explore or distance; or
    tsrm-regret, a deviation from the paper (tsrm plus the regret term of the pathfinding stage, ``k_regret``)."""
    preset: str = "paper"
    """Agent size preset (:data:`tsnav.agent.PRESETS`): the network sizes a recipe's ``[agent]`` section (or the
    ``--dropout``-style options) changes field by field."""
    lr: float = 1e-4
    """Adam learning rate (paper IV-A: 1e-4; a higher one may be needed at CPU scale)."""
    amsgrad: bool = True
    """Adam with the AMSGrad correction, as the lineage's shared optimizer."""
    gamma: float = 0.99
    """Discount factor."""
    gae_tau: float = 1.0
    """GAE lambda (the lineage's tau = 1.0: discounted returns minus the value)."""
    entropy_coef: float = 0.01
    """Weight of the entropy bonus."""
    value_coef: float = 0.5
    """Weight of the value loss (itself 0.5 (R - V)^2 per step)."""
    max_grad_norm: float = 100.0
    """Gradient-norm clip."""
    rollout_steps: int = 30
    """T, steps per rollout and update (per episode row); backpropagation through time over T steps."""
    max_steps: int = 30
    """Training episode length: truncated after this many actions (the lineage trains with 30)."""
    num_envs: int = 16
    """Batched trainer: episodes stepped together per update, over all processes (each steps ``num_envs /
    procs`` of them; with ``ranks`` ``staggered`` each process steps ``num_envs`` for its own update)."""
    procs: int = 1
    """Batched trainer: CPU processes sharing the episodes of an update, gradients averaged (``tsnav train
    --procs N`` starts them; ``torchrun`` may launch them instead). Part of the run's identity: a run is
    deterministic for a given (seed, procs)."""
    ranks: str = "split"
    """Batched trainer with ``procs`` > 1, how the processes share the work (:data:`RANK_MODES`): ``split`` (default)
    -- they share the ``num_envs`` episodes of each update and average their gradients, so N processes compute one
    process's update; ``staggered`` -- each steps ``num_envs`` episodes of its own, and every round applies the N
    gradients one after another (N updates of ``num_envs`` episodes per round; rank r's gradient was computed on
    weights r updates old, as an A3C worker's is). ``split`` is bounded by the work of a rank that does not shrink
    with its rows (BENCHMARKS.md); ``staggered`` is not. Part of the run's identity."""
    workers: int = 14
    """A3C: worker processes, one episode each (paper: 14)."""
    seed: int = 0
    """Seed of initialisation, episode sampling, dropout and actions (rank / worker offsets are added)."""
    c_target: float = C_TARGET
    """Stage-switch threshold C_target on the target confidence (paper IV-A: 0.7)."""
    success_distance: float = 1.0
    """Done succeeds with the target in view within this many metres (paper III-A; the ``paper`` protocol)."""
    protocol: str = DEFAULT_PROTOCOL
    """Success protocol of the run (:mod:`tsnav.protocol`): ``paper`` or ``lineage``. It sets the success mask
    of the reward's success term and distance fields (TSRM) and the training episodes; evaluations compare it
    with their episode list's."""
    episodes: int | None = None
    """Budget: stop after this many finished training episodes (paper: 1.5 M). All budgets None -> 1.5 M."""
    updates: int | None = None
    """Budget: stop after this many optimizer updates."""
    minutes: float | None = None
    """Budget: stop after this many minutes of training (summed over resumed sessions)."""
    checkpoint_every: int = 100
    """Updates between checkpoints. The batched trainer starts fresh episodes after each checkpoint so that a
    resumed run continues exactly like an uninterrupted one."""
    milestone_every: int | None = None
    """Also keep every checkpoint whose update is a multiple of this (None: only the two newest), so that a
    checkpoint can be chosen on a validation split afterwards."""
    log_every: int = 10
    """Updates between log lines (JSONL, TensorBoard)."""
    threads: int = 1
    """Intra-op CPU threads per process (1: the network's small ops gain nothing from more, and spinning
    threads of several processes on few cores slow each other down badly)."""
    precision: str = "fp32"
    """``fp32``, or ``bf16``: the training rollouts' forward passes run under ``torch.autocast`` in bfloat16 (the
    matrix products; weights, gradients' accumulation, optimizer and LSTM state stay float32). About 2.1-2.3x the
    ``paper`` preset's throughput on a CPU with AVX512-BF16 (BENCHMARKS.md); slower than fp32 on CPUs without
    bfloat16 instructions. Evaluation always runs in float32."""
    device: str = "auto"
    """``auto`` (CUDA when available), ``cpu`` or ``cuda`` (batched trainer; A3C workers run on the CPU)."""
    mirror: bool = False
    """A deviation from the paper (training-data augmentation), off by default: also train on the mirror image of
    every training room (:meth:`Scene.mirrored <tsnav.data.reader.Scene.mirrored>`: RotateLeft and RotateRight
    trade places, frames flipped left to right), which doubles the rooms; it needs the features and detection
    tables of the flipped frames (``tsnav features --mirror``, ``tsnav detect --mirror``). Evaluation is on the
    rooms as they are."""

    distance_increase_scale: float = 1.0
    """A deviation from the paper when not 1.0, off by default: the distance reward of a pathfinding step that
    increases the distance to the target is multiplied by this (:attr:`RewardConfig.distance_increase_scale
    <tsnav.tsrm.reward.RewardConfig.distance_increase_scale>`), so that a detour, such as turning the long way
    round, costs more than the slack alone."""
    lr_schedule: str = "constant"
    """A deviation from the paper when not ``constant`` (the paper's Adam runs at one rate), off by default: the
    learning rate of update ``u`` (0-based) falls from :attr:`lr` at update 0 to :attr:`lr_final` at update
    :attr:`lr_decay_updates` and stays there: ``linear``, or ``cosine`` (a half cosine). It is a function of the
    update counter, which a checkpoint holds, so a resumed run continues the same schedule (A3C: of the shared
    update counter, read by each worker before its step)."""
    lr_final: float = 0.0
    """The learning rate at the end of a ``linear`` or ``cosine`` :attr:`lr_schedule` (not used by ``constant``)."""
    lr_decay_updates: int | None = None
    """Updates over which a ``linear`` or ``cosine`` :attr:`lr_schedule` decays; None: the ``updates`` budget. Part
    of the run's identity: a run resumed with another ``updates`` budget and no ``lr_decay_updates`` is refused
    (its schedule would change), so to train a scheduled run past its budget name the horizon it started with."""
    reward_settings: dict = field(default_factory=dict)
    """The reward's constants where they differ from the paper's: fields of
    :class:`~tsnav.tsrm.reward.RewardConfig` (K_e ``k_explore``, K_d ``k_distance``, ``collision_penalty``,
    ``slack``, ``success_reward``, ``failed_done``, ``exact_area``, ``k_regret``, and ``area``: the trapezoid's distances
    ``near_level``, ``far_level``, ``near_down``, ``far_down``) other than ``variant`` (:attr:`reward`) and
    ``distance_increase_scale``. A recipe's ``[reward]`` section and the ``--k-distance``-style options set
    them; kept canonical (only values that differ from the defaults), so a run without them equals one that
    names the defaults."""

    def __post_init__(self):
        if self.algo not in ALGOS:
            raise ValueError(f"unknown algo {self.algo!r} (choose from {', '.join(ALGOS)})")

        check_protocol(self.protocol)
        if self.precision not in PRECISIONS:
            raise ValueError(f"unknown precision {self.precision!r} (choose from {', '.join(PRECISIONS)})")
        if self.reward not in VARIANTS:
            raise ValueError(f"unknown reward {self.reward!r} (choose from {', '.join(VARIANTS)})")
        for name in (
            "rollout_steps",
            "max_steps",
            "num_envs",
            "workers",
            "checkpoint_every",
            "log_every",
            "threads",
            "procs",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.distance_increase_scale >= 0:
            raise ValueError(f"distance_increase_scale must be >= 0, got {self.distance_increase_scale}")
        own = [k for k in REWARD_OWN if k in self.reward_settings]
        if own:
            raise ValueError(
                f"reward_settings may not hold {', '.join(own)} (TrainConfig.reward and "
                "TrainConfig.distance_increase_scale set them)"
            )
        self.reward_settings = reward_settings_of(self.reward_config())  # checks the values, canonical form
        if not self.lr > 0:
            raise ValueError(f"lr must be positive, got {self.lr}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"unknown lr_schedule {self.lr_schedule!r} (choose from {', '.join(LR_SCHEDULES)})")
        if self.lr_schedule == "constant":
            if self.lr_final != 0.0 or self.lr_decay_updates is not None:
                raise ValueError("lr_final and lr_decay_updates apply to lr_schedule linear or cosine, not constant")
        else:
            if not 0.0 <= self.lr_final <= self.lr:
                raise ValueError(f"lr_final must be in [0, lr = {self.lr}], got {self.lr_final}")
            if self.lr_decay_updates is None and self.updates is None:
                raise ValueError(
                    f"lr_schedule {self.lr_schedule!r} needs a horizon: an updates budget or lr_decay_updates"
                )
            if self.lr_decay_updates is not None and self.lr_decay_updates < 1:
                raise ValueError(f"lr_decay_updates must be >= 1, got {self.lr_decay_updates}")
        for name in ("entropy_coef", "value_coef", "max_grad_norm"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.c_target <= 1.0:
            raise ValueError(f"c_target must be in [0, 1], got {self.c_target}")
        if not 0.0 < self.gamma <= 1.0 or not 0.0 <= self.gae_tau <= 1.0:
            raise ValueError("gamma must be in (0, 1] and gae_tau in [0, 1]")
        if self.procs > 1 and self.algo != "batched":
            raise ValueError(
                f"procs applies to the batched trainer (A3C runs --workers processes), got algo {self.algo!r}"
            )
        if self.ranks not in RANK_MODES:
            raise ValueError(f"unknown ranks mode {self.ranks!r} (choose from {', '.join(RANK_MODES)})")
        if self.ranks == "split" and self.num_envs % self.procs:
            raise ValueError(f"num_envs {self.num_envs} does not split evenly over procs={self.procs} processes")
        if self.ranks == "staggered" and self.procs > 1:  # a round makes procs updates: boundaries fall on rounds
            for name in ("checkpoint_every", "log_every", "milestone_every", "updates"):
                v = getattr(self, name)
                if v is not None and v % self.procs:
                    raise ValueError(
                        f"ranks 'staggered' makes {self.procs} updates per round: {name} must be a "
                        f"multiple of procs={self.procs}, got {v}"
                    )
        if self.milestone_every is not None and self.milestone_every < 1:
            raise ValueError(f"milestone_every must be >= 1, got {self.milestone_every}")
        for name in BUDGET_FIELDS:
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise ValueError(f"{name} budget must be positive, got {v}")

    @property
    def budget(self) -> dict:
        """The active budget: the given ones, else ``{"episodes": 1.5 M}`` (paper IV-A)."""
        b = {k: getattr(self, k) for k in BUDGET_FIELDS if getattr(self, k) is not None}
        return b or {"episodes": PAPER_EPISODES}

    def budget_reached(self, progress: dict) -> bool:
        """Whether ``progress`` (``update``, ``episodes``, ``seconds``) has used up the budget."""
        b = self.budget
        return (
            ("episodes" in b and progress["episodes"] >= b["episodes"])
            or ("updates" in b and progress["update"] >= b["updates"])
            or ("minutes" in b and progress["seconds"] >= 60.0 * b["minutes"])
        )

    def budget_fraction(self, progress: dict) -> float:
        """Fraction of the budget used (the largest over its parts), for progress bars."""
        b = self.budget
        parts = [
            progress["episodes"] / b["episodes"] if "episodes" in b else 0.0,
            progress["update"] / b["updates"] if "updates" in b else 0.0,
            progress["seconds"] / (60.0 * b["minutes"]) if "minutes" in b else 0.0,
        ]
        return min(1.0, max(parts))

    @property
    def lr_horizon(self) -> int | None:
        """Updates over which the learning rate decays (:attr:`lr_decay_updates`, else the ``updates`` budget);
        None with a ``constant`` :attr:`lr_schedule`."""
        if self.lr_schedule == "constant":
            return None
        return self.lr_decay_updates if self.lr_decay_updates is not None else self.updates

    def lr_at(self, update: int) -> float:
        """The learning rate of the update that follows ``update`` finished updates (:attr:`lr_schedule`)."""
        if self.lr_schedule == "constant":
            return self.lr
        if self.lr_schedule == "linear":
            return linear_decay(update, self.lr_horizon, self.lr, self.lr_final)
        return warmup_cosine(update, self.lr_horizon, self.lr, 0, self.lr_final)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        return from_fields(cls, d, "training config")

    def identity(self) -> dict:
        """The fields that define the run (everything but the budget; with a learning-rate schedule its horizon,
        :attr:`lr_horizon`, as ``lr_decay_updates``)."""
        out = {k: v for k, v in asdict(self).items() if k not in BUDGET_FIELDS}
        if self.lr_schedule != "constant":
            out["lr_decay_updates"] = self.lr_horizon
        return out

    def reward_config(self) -> RewardConfig:
        """The :class:`~tsnav.tsrm.reward.RewardConfig` of this run: variant ``reward``, the paper's constants
        changed by :attr:`reward_settings`, and ``distance_increase_scale``."""
        base = RewardConfig(variant=self.reward, distance_increase_scale=self.distance_increase_scale)
        settings = dict(self.reward_settings)
        area = settings.pop("area", None)
        unknown = set(settings) - {f.name for f in fields(RewardConfig)}
        if unknown:
            raise ValueError(f"reward_settings: no reward setting {', '.join(sorted(unknown))}")
        if area:
            settings["area"] = replace(base.area, **area)
        return replace(base, **settings)
