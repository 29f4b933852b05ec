"""The stage switch of paper III-B ("Dividing point"): one rule, one per-episode state.

An episode starts in the searching stage and enters the pathfinding stage, for good, at the first frame (the
start frame included) whose target confidence exceeds ``C_target`` (:data:`tsnav.constants.C_TARGET`, 0.7 in
paper IV-A). The confidence is the detector's when the bank has one installed, else the ground-truth
"target in frame" flag as 1.0 / 0.0 (``SceneBank.stage_confidence``).

:class:`StageSwitch` follows ``B`` episodes in the manner of a habitat measure: :meth:`~StageSwitch.reset`
when episodes start, :meth:`~StageSwitch.update` after every step. Its one owner is the env
(:class:`~tsnav.sim.batch.BatchEnv` steps it and hands its :attr:`~StageSwitch.searching` mask to a reward that
declares it uses the stage, as habitat-lab's measures declare what they depend on): the TSRM reward (which
term a step earns), the training statistics (SSR, SSSPL, NSNPL of training episodes), the evaluation runner
and the episode pictures all read the stage from the env's switch; :func:`switch_frame` is the same rule over
one recorded path.

The threshold has one home: the bank's ``c_target`` (:class:`~tsnav.sim.batch.SceneBank`, built from the
run's ``TrainConfig.c_target`` / an evaluation's ``EvalConfig.c_target``); a switch over the bank applies
``bank.stage_mask`` and keeps no copy of it.
"""

from __future__ import annotations

import numpy as np

from ..constants import C_TARGET

SEARCHING, PATHFINDING = 0, 1
"""The two stages of paper III-B as the values of :attr:`StageSwitch.stage`."""


def above_threshold(confidence: np.ndarray, c_target: float = C_TARGET) -> np.ndarray:
    """Where a frame starts the pathfinding stage: ``confidence > c_target`` (strictly above, paper III-B)."""
    return np.asarray(confidence) > c_target


def switch_frame(confidence_along_path: np.ndarray, c_target: float = C_TARGET) -> int:
    """Index of the first frame of a path (start frame = 0) whose target confidence exceeds ``c_target``, or
    -1 when the episode never leaves the searching stage."""
    above = above_threshold(confidence_along_path, c_target)
    return int(np.argmax(above)) if above.any() else -1


class StageSwitch:
    """Two-stage state of ``B`` episodes over a :class:`~tsnav.sim.batch.SceneBank`.

    Per episode (``(B,)`` arrays):
        entered: in the pathfinding stage (the switch happened; it never reverts).
        switch_step: actions output before the switching frame (0: the start frame; -1: not yet).
        switch_length: movement actions output before the switching frame (0 while searching).
        switch_state: global state id of the switching frame (the start state while searching).
    """

    def __init__(self, bank, c_target: float | None = None, confidence: np.ndarray | None = None, num_envs: int = 0):
        """Without ``c_target`` and ``confidence`` the switch applies the bank's own rule (``bank.stage_mask``:
        ``bank.stage_confidence`` above ``bank.c_target``). Either overrides the bank's for this switch (an
        evaluation at its own C_target, a test's confidence table)."""
        if c_target is None and confidence is None:
            self.switches = bank.stage_mask  # (S, C): this frame starts the pathfinding stage
        else:
            c = float(bank.c_target if c_target is None else c_target)
            if not 0.0 <= c <= 1.0:
                raise ValueError(f"c_target must be in [0, 1], got {c}")
            conf = bank.stage_confidence if confidence is None else np.asarray(confidence, dtype=np.float32)
            if conf.shape != (bank.num_states, bank.num_categories):
                raise ValueError(
                    f"confidence must have shape ({bank.num_states}, {bank.num_categories}), got {conf.shape}"
                )
            self.switches = above_threshold(conf, c)
        self._alloc(num_envs)

    def _alloc(self, b: int) -> None:
        self.target = np.zeros(b, dtype=np.int64)
        self.entered = np.zeros(b, dtype=bool)
        self.switch_step = np.full(b, -1, dtype=np.int64)
        self.switch_length = np.zeros(b, dtype=np.int64)
        self.switch_state = np.zeros(b, dtype=np.int64)

    @property
    def searching(self) -> np.ndarray:
        """``(B,)`` bool: the episode is still in the searching stage."""
        return ~self.entered

    @property
    def stage(self) -> np.ndarray:
        """``(B,)`` int8 stage of every episode: :data:`SEARCHING` or :data:`PATHFINDING`."""
        return np.where(self.entered, PATHFINDING, SEARCHING).astype(np.int8)

    def reset(self, mask: np.ndarray, start_state: np.ndarray, target: np.ndarray) -> None:
        """Start the episodes where ``mask`` is True from global ``start_state`` with category ``target``
        (``(B,)`` arrays); a start frame above the threshold starts in the pathfinding stage."""
        mask = np.asarray(mask, dtype=bool)
        if len(mask) != len(self.entered):
            self._alloc(len(mask))
        rows = np.flatnonzero(mask)
        s = np.asarray(start_state, dtype=np.int64)[rows]
        g = np.asarray(target, dtype=np.int64)[rows]
        at_start = self.switches[s, g]
        self.target[rows] = g
        self.entered[rows] = at_start
        self.switch_step[rows] = np.where(at_start, 0, -1)
        self.switch_length[rows] = 0
        self.switch_state[rows] = s

    def update(
        self,
        new_state: np.ndarray,
        steps: np.ndarray,
        path_length: np.ndarray | None = None,
        active: np.ndarray | None = None,
    ) -> np.ndarray:
        """Account one step that led every episode to ``new_state`` after ``steps`` actions (``path_length``
        movement actions); only ``active`` rows count. Returns the ``(B,)`` mask of episodes that switched now."""
        new_state = np.asarray(new_state, dtype=np.int64)
        new = ~self.entered & self.switches[new_state, self.target]
        if active is not None:
            new &= np.asarray(active, dtype=bool)
        self.entered |= new
        self.switch_step[new] = np.asarray(steps)[new]
        if path_length is not None:
            self.switch_length[new] = np.asarray(path_length)[new]
        self.switch_state[new] = new_state[new]
        return new

    # -- one episode in scalars (the single Gymnasium env; references: reset / update above) -----------------
    def reset_one(self, start_state: int, target: int) -> bool:
        """:meth:`reset` of a batch of one episode (``B`` = 1), in Python scalars; returns whether it starts in
        the searching stage (``searching[0]``)."""
        if len(self.entered) != 1:
            self._alloc(1)
        at_start = bool(self.switches[start_state, target])
        self.target[0] = target
        self.entered[0] = at_start
        self.switch_step[0] = 0 if at_start else -1
        self.switch_length[0] = 0
        self.switch_state[0] = start_state
        return not at_start

    def update_one(self, new_state: int, steps: int, path_length: int, active: bool) -> bool:
        """:meth:`update` of a batch of one episode, in Python scalars; returns whether it switched now."""
        new = active and not self.entered[0] and bool(self.switches[new_state, self.target[0]])
        if new:
            self.entered[0] = True
            self.switch_step[0] = steps
            self.switch_length[0] = path_length
            self.switch_state[0] = new_state
        return new
