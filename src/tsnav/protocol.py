"""Success protocols: the rule that makes Done a success, and how the episodes and metrics that go with it
are counted. One is chosen for an episode list, a training run and an evaluation, and saved with each.

``paper`` (the default; paper section III-A)
    Done succeeds when an instance of the target category is in view and within 1.0 m of the agent
    (:meth:`tsnav.data.reader.Scene.category_visible_within`). Fixed episode lists leave out starts that
    already succeed (no path to measure); SPL is ``L* / max(L, L*)`` with movement actions counted (Done not),
    and the ``L>=5`` subset holds the episodes with ``L* >= 5``.

``lineage`` (the evaluator of the methods of the paper's Table I: SAVN -> VTNet -> DOA -> IOM / DAT)
    Done succeeds when any object id of the target category lists the current state key in the scene's
    ``visible_object_map_1.5.json``: IOM ``full_eval.py`` -> ``episodes/basic_episode.py::judge`` loops over
    the episode's ``task_data`` (the target type's object ids) and asks the offline controller's
    ``object_is_visible(id)``, i.e. ``str(state) in visible_map[id]``. Its test lists keep starts that already
    see the target, so ``lineage`` keeps them too. Its ``compute_spl`` (``runners/train_util.py`` of that code)
    divides ``best_path_len`` - from the offline controller's ``shortest_path_to_target``
    (``datasets/offline_controller_with_small_rotation.py``), ``len(nx.shortest_path(...))``, the number of
    *states* on a shortest path to a state where the target is listed, start included, hence
    ``L* + 1`` in tsnav's movement-action count - by ``player.eps_len``, every action output, Done included
    (``L + 1`` for an episode that succeeded, since success needs Done): SPL = ``(L* + 1) / (L + 1)`` on
    success, so a start that already sees the target and outputs Done at once scores SR 1 and SPL 1, and one
    that walks two steps first scores SPL 1/3. Its ``get_bucketed_metrics`` files an episode under
    ``GreaterThan/5`` when ``best_path_len >= 5``, i.e. ``L* >= 4`` in movement actions; tsnav's ``L>=5`` row
    under ``lineage`` is that bucket (start-success episodes, ``L* = 0``, are never in it). Test episodes run
    100 steps under both protocols (some of the lineage's val runners give living rooms 200; tsnav does not).
    These functions were read in the SAVN / VTNet / DOA code the lineage shares (the same ``judge``,
    ``compute_spl``, ``get_bucketed_metrics`` and controller in each); IOM's own repository was not at hand.

In the worlds tsnav builds (``tsnav world``, the procedural and the ``ithor-real`` rooms),
``visible_object_map_1.5.json`` lists an object at a state when it shows at least the scene's ``min_pixels``
pixels and its footprint is within 1.5 m of the agent on the floor plane (``tsnav.world.build``). The two
protocols then differ only in the radius: every ``paper`` success state is a ``lineage`` one, not the reverse.
Data imported from the lineage carries AI2-THOR's own map (its 1.5 m ``visibilityDistance`` from the camera),
and without object distances the ``paper`` rule falls back to that same map.

This module names the protocols and their counting conventions (layer 0); the one place that turns a
protocol into a success mask is :meth:`tsnav.data.reader.Scene.success_table`.
"""

from __future__ import annotations

from dataclasses import dataclass

PAPER = "paper"
LINEAGE = "lineage"
#: The protocols, default first.
PROTOCOLS = (PAPER, LINEAGE)
#: The protocol of every existing figure (the paper's text).
DEFAULT_PROTOCOL = PAPER


@dataclass(frozen=True)
class ProtocolSpec:
    """What a protocol fixes besides its success mask."""

    name: str
    rule: str
    """One line for table headers."""
    keeps_start_success: bool
    """Fixed episode lists (and the training sampler) keep starts that already succeed."""
    length_offset: int
    """Added to both lengths of the SPL ratio: 0 (paper: movement actions) or 1 (lineage: states on the
    shortest path over actions output, Done included)."""


SPECS = {
    PAPER: ProtocolSpec(PAPER, "Done succeeds with the target in view within 1.0 m (paper III-A)", False, 0),
    LINEAGE: ProtocolSpec(
        LINEAGE,
        "Done succeeds with a target id listed at the state in visible_object_map_1.5.json "
        "(the lineage's judge); start-success episodes kept",
        True,
        1,
    ),
}


def check_protocol(name: str | None) -> str:
    """``name`` when it is a protocol (None gives the default); ``ValueError`` in one line otherwise."""
    if name is None:
        return DEFAULT_PROTOCOL
    if name not in SPECS:
        raise ValueError(f"unknown success protocol {name!r} (choose from {', '.join(PROTOCOLS)})")
    return name


def spec(name: str | None) -> ProtocolSpec:
    """The :class:`ProtocolSpec` of ``name`` (checked by :func:`check_protocol`)."""
    return SPECS[check_protocol(name)]


def protocol_of(meta: dict | None) -> str:
    """The protocol recorded in an output's metadata; files written before protocols existed are ``paper``."""
    return check_protocol((meta or {}).get("protocol") or DEFAULT_PROTOCOL)


def protocol_line(evaluated: str, trained: str | None = None) -> str:
    """The header line every table prints: the protocol evaluated under (and trained under, when known)."""
    s = f"protocol: {evaluated}"
    if trained is not None and trained != evaluated:
        s += f" (agent trained under {trained})"
    elif trained is not None:
        s += " (trained and evaluated)"
    return s + f" - {SPECS[evaluated].rule}"
