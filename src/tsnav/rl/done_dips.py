"""Done dips: stretches of training in which the policy all but stopped taking Done (RESULTS.md, "Training
stability").

With the exploration reward, walking on earns more than an early Done in most states at the start of training,
so the probability of Done falls towards 0, almost every training episode runs to its step limit and no success
is learnt until Done comes back. :func:`done_dips` finds those stretches in a run's ``log.jsonl`` so that
experiments can say how often they happen, on which rows, and how many updates they cost. Each log line carries
``done_rate`` (the share of the update's actions that were Done) and ``length`` (mean length of the episodes that
ended), so ``done_rate * length`` is about the share of episodes that ended with Done rather than at the step
limit; a dip is a stretch where it stays below :data:`DIP_DONE_SHARE`. (A slowly learning policy whose episodes
mostly still end with Done is not in a dip, however rarely its Done succeeds.)
"""

from __future__ import annotations

from pathlib import Path

from .logger import read_log

#: A log line is "in a dip" when fewer than this share of its episodes ended with Done (an untrained six-action
#: policy ends almost all of them with Done; the collapsed runs measured here fell to 2-3 %).
DIP_DONE_SHARE = 0.05


def done_share(record: dict) -> float | None:
    """About the share of a log record's episodes that ended with Done: ``done_rate * length``, at most 1; None
    when the record lacks either (logs written before they existed)."""
    if record.get("done_rate") is None or record.get("length") is None:
        return None
    return min(1.0, float(record["done_rate"]) * float(record["length"]))


def done_dips(records: list[dict], threshold: float = DIP_DONE_SHARE) -> list[dict]:
    """Maximal runs of consecutive log records whose :func:`done_share` is below ``threshold``: ``{"start",
    "end"}`` (the first and last update of the run), ``"updates"`` (``end - start`` plus one logging interval),
    ``"min_done_prob"`` (the policy's lowest mean Done probability in it, when logged) and ``"recovered"`` (a later
    record is back at or above the threshold). Records without the fields are skipped."""
    rows = [r for r in records if done_share(r) is not None and r.get("update") is not None]
    dips, cur = [], None
    for i, r in enumerate(rows):
        if done_share(r) < threshold:
            if cur is None:
                prev = rows[i - 1]["update"] if i > 0 else 0
                cur = {"start": int(r["update"]), "step": int(r["update"] - prev), "probs": []}
            cur["end"] = int(r["update"])
            if r.get("done_prob") is not None:
                cur["probs"].append(float(r["done_prob"]))
        elif cur is not None:
            dips.append({**cur, "recovered": True})
            cur = None
    if cur is not None:
        dips.append({**cur, "recovered": False})
    return [
        {
            "start": d["start"],
            "end": d["end"],
            "min_done_prob": min(d["probs"]) if d["probs"] else None,
            "recovered": d["recovered"],
            "updates": d["end"] - d["start"] + d["step"],
        }
        for d in dips
    ]


def run_done_dips(run_dir: str | Path, threshold: float = DIP_DONE_SHARE) -> list[dict]:
    """:func:`done_dips` of a training run folder's ``log.jsonl``."""
    return done_dips(read_log(run_dir), threshold)
