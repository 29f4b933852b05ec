"""docs/RESULTS.md, rendered: the paper's tables with tsnav's measured figures beside its published ones.

One command renders the page from three sources and nothing else, so that no figure is typed twice:

* ``docs/results/index.json``: which result file stands for which table, and each table's setting and command
  (words only);
* the result files it names (``docs/results/*.json``, written by ``tsnav experiment``: per-seed figures, means and
  95 % intervals under every protocol);
* the shipped agents' model cards (``tsnav/agent/weights/*/card.json``, written by ``tsnav release eval
  --update-card``), and the paper's published figures (``report/data/paper.json``, :func:`published_figures`).

``python -m tsnav.report.results_page`` writes the page and the short Table I of README.md (between
:data:`README_BEGIN` and :data:`README_END`); ``--check`` exits with 1 when a committed page differs from what it
renders (``tests/project/test_docs_pages.py`` runs the same comparison).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..atomic import atomic_write_text
from .claims import check_claims, published_figures

#: Where the shipped agents' cards live (package data of ``tsnav.agent``; read as JSON files, no import).
WEIGHTS = Path(__file__).resolve().parent.parent / "agent" / "weights"
METRICS = ("SR", "SPL", "SSR", "SSSPL", "NSNPL")
PROTOCOL_SENTENCE = (
    "Two success rules are used (`--protocol`): `paper`, the paper's own (Done with the target in view within 1.0 m, "
    "III-A), and `lineage`, the rule of the evaluator the Table I methods share (Done where an object of the target's "
    "type is listed in AI2-THOR's `visible_object_map_1.5.json`); the headline agent is trained and measured under "
    "`lineage`."
)


def repo_root() -> Path:
    """The checkout this module runs from (``src/tsnav/report`` -> the folder holding ``docs/``)."""
    return Path(__file__).resolve().parents[3]


def _code(command: str) -> list[str]:
    """The lines of a fenced block holding ``command`` (the commands that made an entry's figures)."""
    return ["```", command, "```"]


def _section_head(e: dict) -> list[str]:
    """The first lines of an index entry's section: its title, its text with a link to its data, its commands."""
    return [
        f"## {e['title']}",
        "",
        f"{e['about']} Data: [{e['file']}](results/{e['file']}).",
        "",
        *_code(e["command"]),
        "",
    ]


def _pct(x: float) -> str:
    return f"{100 * x:.2f}"


def _pair(vals, i: int, j: int) -> str:
    return f"{vals[i]:.2f} / {vals[j]:.2f}"


def read_cards(weights: Path = WEIGHTS) -> dict[str, dict]:
    """Name -> model card of every shipped agent folder under ``weights``, the default one first."""
    cards = {
        p.name: json.loads((p / "card.json").read_text())
        for p in sorted(weights.iterdir())
        if (p / "card.json").exists()
    }
    return dict(sorted(cards.items(), key=lambda kv: not kv[1].get("default")))


def _card_row(card: dict, protocol: str, policy: str, split: str = "test") -> dict | None:
    for r in card.get("figures", {}).get(split, {}).get("rows", []):
        if r["protocol"] == protocol and r["policy"] == policy:
            return r
    return None


def _sr_spl(row: dict | None, subset: str) -> str:
    if row is None:
        return "not measured"
    m = row["metrics"][subset]
    return f"{_pct(m['SR'])} / {_pct(m['SPL'])}"


def table1_rows(
    index: dict, cards: dict, paper: dict, select: dict | None = None, results: Path | None = None
) -> list[str]:
    """The rows of Table I: the published methods, then tsnav's agents and references per protocol. ``select``
    (the index's ``readme`` entry) keeps only the published methods, agents, references and protocols it names.
    RoboTHOR figures come from the files the index's ``table1.robothor`` names per agent (the ``results.json`` of
    ``tsnav release eval`` on RoboTHOR, copied to ``docs/results/``); an agent without one is "not yet measured"."""
    spec = index["table1"]
    keep = select or {}
    lines = [
        "| method | measured on | iTHOR ALL | iTHOR L>=5 | RoboTHOR ALL | RoboTHOR L>=5 |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for r in paper["table1"]["rows"]:
        if select and r["method"] not in keep["published"]:
            continue
        it, rb = r["ithor"], r["robothor"]
        name = f"**{r['method']}**" if r.get("ours") else r["method"]
        lines.append(
            f"| {name} | published (paper's Table I) | {_pair(it, 0, 1)} | {_pair(it, 2, 3)} | "
            f"{_pair(rb, 0, 1)} | {_pair(rb, 2, 3)} |"
        )
    robothor = {name: robothor_entry(v, results) for name, v in (spec.get("robothor") or {}).items()}
    ref = spec["reference_agent"]
    rows = [(name, "agent") for name in keep.get("agents", spec["agents"])] + [
        (ref, p) for p in keep.get("references", spec["references"])
    ]
    for protocol in keep.get("protocols", ("lineage", "paper")):
        for name, policy in rows:
            card = cards[name]
            row = _card_row(card, protocol, policy)
            rob_agent, rob_rows, rob_n = robothor.get(name, (None, [], None))
            if policy == "agent":
                label = f"tsnav `{name}`" + (f" (RoboTHOR: `{rob_agent}`)" if rob_agent and rob_agent != name else "")
                if card.get("default") and protocol == "lineage":
                    label = f"**{label}** (shipped default)"
            else:
                rob_det = cards.get(rob_agent, {}).get("detector_shipped") if rob_agent and rob_rows else None
                label = (
                    f"{policy} (map + shortest path, `{card.get('detector_shipped', '?')}` switch"
                    + (f"; RoboTHOR `{rob_det}`)" if rob_det else ")")
                    if policy == "scripted explorer"
                    else policy
                )
            n = card.get("figures", {}).get("test", {}).get("episodes", "?")
            rob = next((r for r in rob_rows if (r["protocol"], r["policy"]) == (protocol, policy)), None)
            rob_cells = (
                f"{_sr_spl(rob, 'ALL')} | {_sr_spl(rob, 'L>=5')}" if rob else "not yet measured | not yet measured"
            )
            where = f"{n} test episodes" + (f", RoboTHOR {rob['episodes']} val episodes" if rob else "")
            lines.append(
                f"| {label} | {where}, `{protocol}` | {_sr_spl(row, 'ALL')} | {_sr_spl(row, 'L>=5')} | {rob_cells} |"
            )
    return lines


def robothor_entry(value, results: Path) -> tuple[str | None, list[dict], int | None]:
    """``(agent, rows, episodes)`` of one entry of the index's ``table1.robothor``: a results file of ``tsnav release
    eval`` on RoboTHOR (``{"agent": NAME, "results": FILE}``, or just ``FILE`` for the row's own agent)."""
    if isinstance(value, str):
        value = {"results": value}
    res = json.loads((results / value["results"]).read_text())
    rows = res["rows"]
    return value.get("agent") or res.get("agent"), rows, max((r["episodes"] for r in rows), default=None)


def table1(index: dict, cards: dict, paper: dict, results: Path) -> list[str]:
    """Table I: the paper's and its peers' published SR / SPL beside tsnav's agents from their model cards."""
    return (
        [
            "## Table I: comparison with the published methods",
            "",
            "SR / SPL in percent. The published rows are copied from the paper's Table I (each method on its own "
            "AI2-THOR and RoboTHOR test episodes, counted by the lineage's evaluator). tsnav's rows are measured here "
            f"on {index['episodes']}, under the protocol each row names; "
            + (
                "RoboTHOR on the RoboTHOR challenge's 1,800 val episodes in the 15 val apartments of the "
                "`robothor-real` world (those whose start is a state of tsnav's graph), by the RoboTHOR agent the "
                "row names, trained on the 60 train apartments (`tsnav release eval --agent NAME`)."
                if index["table1"].get("robothor")
                else "RoboTHOR is not measured yet."
            ),
            "",
        ]
        + table1_rows(index, cards, paper, results=results)
        + [
            "",
            "The scripted explorer holds the room's map and walks the true shortest path once its detector "
            "switch fires: an upper reference, not a learned agent. Under `lineage`, L>=5 is the lineage's bucket "
            "(its `best_path_len` >= 5, i.e. an optimal path of at least 4 actions).",
        ]
    )


def _cell(metrics: dict, subset: str, metric: str) -> str:
    v = (metrics.get(subset) or {}).get(metric) or {}
    if v.get("mean") is None:
        return "-"
    ci = v.get("ci95")
    return f"{v['mean']:.2f}" + (f" ± {ci:.2f}" if ci is not None else "")


def experiment_table(title: str, paper_key: str, entries: list[dict], paper: dict, results: Path) -> list[str]:
    """Table II or III: for each listed result file, the paper's ALL figures beside tsnav's under the protocol the
    agents were trained under, then tsnav's under the other protocol."""
    lines = [f"## {title}", ""]
    published = paper[paper_key]
    cols = published["columns"]
    if not entries:
        return lines + ["Not run yet."]
    for e in entries:
        res = json.loads((results / e["file"]).read_text())
        proto = res.get("protocol", "paper")
        lines += [
            f"Measured at {e['setting']}; {res['rows'][0].get('n', '?')} seeds per row, mean ± half-width "
            f"of the 95 % t-interval, in percent, on the test episodes of Table I (ALL episodes). "
            f"Per seed, L>=5, Welch tests and claim checks: [{e['details']}](results/{e['details']}); "
            f"data: [{e['file']}](results/{e['file']}).",
            "",
            *_code(e["command"]),
            "",
            "| row | " + " | ".join(f"{m} paper | {m} tsnav `{proto}`" for m in cols) + " |",
            "| --- | " + " | ".join("---: | ---:" for _ in cols) + " |",
        ]
        seen = set()
        for row in res["rows"]:
            rid = row["row"]
            pub = published["rows"].get(rid, {}).get("ALL")
            seen.add(rid)
            cells = [
                f"{pub[i]:.2f} | {_cell(row['metrics'], 'ALL', m)}" if pub else f"- | {_cell(row['metrics'], 'ALL', m)}"
                for i, m in enumerate(cols)
            ]
            lines.append(f"| {row['label']} | " + " | ".join(cells) + " |")
        for rid, pub in published["rows"].items():
            if rid not in seen:
                label = published.get("labels", {}).get(rid, rid)
                lines.append(
                    f"| {label} (published; not run here) | "
                    + " | ".join(f"{pub['ALL'][i]:.2f} | -" for i in range(len(cols)))
                    + " |"
                )
        for other, ores in (res.get("other_protocols") or {}).items():
            lines += [
                "",
                f"The same agents under `{other}` (tsnav only; trained under `{proto}`):",
                "",
                "| row | " + " | ".join(cols) + " |",
                "| --- | " + " | ".join("---:" for _ in cols) + " |",
            ]
            for row in ores["rows"]:
                lines.append(f"| {row['label']} | " + " | ".join(_cell(row["metrics"], "ALL", m) for m in cols) + " |")
        lines.append("")
    return lines[:-1]


def fig4(index: dict, results: Path) -> list[str]:
    """Fig. 4: for each listed threshold experiment, its picture, every metric per C_target (mean ± half-width of
    the 95 % t-interval over the seeds, the best mean of each metric in bold) and the reading of the paper's claim
    (C_target = 0.7 best) by :func:`tsnav.report.claims.check_claims`, as `tsnav claims` prints it."""
    lines = ["## Fig. 4: the dividing-point threshold C_target", ""]
    if not index.get("fig4"):
        return lines + [f"Fig. 4 is {index.get('fig4_not_run', 'not run yet.')}"]
    for e in index["fig4"]:
        res = json.loads((results / e["file"]).read_text())
        rows = sorted(res["rows"], key=lambda r: (r.get("c_target") is None, r.get("c_target") or 0.0))
        details = (
            f"per seed, L>=5 and Welch tests: [{e['details']}](results/{e['details']}); " if e.get("details") else ""
        )
        lines += [
            f"Measured at {e['setting']}; {rows[0].get('n', '?')} seeds per threshold, mean ± half-width of the 95 % "
            f"t-interval, in percent, on validation episodes under `{res.get('protocol', 'paper')}` (ALL episodes); "
            f"{details}data: [{e['file']}](results/{e['file']}).",
            "",
            *_code(e["command"]),
            "",
        ]
        if e.get("picture"):
            lines += [
                f"![Fig. 4 at this setting: each metric over C_target, the best mean starred]({e['picture']})",
                "",
            ]
        best = {}
        for m in METRICS:
            means = [(r["metrics"].get("ALL", {}).get(m, {}).get("mean"), r["row"]) for r in rows]
            means = [x for x in means if x[0] is not None]
            if means:
                best[m] = max(means)[1]
        lines += [
            "| C_target | " + " | ".join(METRICS) + " |",
            "| ---: | " + " | ".join("---:" for _ in METRICS) + " |",
        ]
        for row in rows:
            cells = []
            for m in METRICS:
                c = _cell(row["metrics"], "ALL", m)
                cells.append(f"**{c}**" if best.get(m) == row["row"] and c != "-" else c)
            label = f"{row['c_target']:.1f}" if row.get("c_target") is not None else row["label"]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        checks = check_claims({"threshold": res}, subsets=("ALL",))
        if checks:
            lines += ["", f"The paper's claim, {checks[0]['text']}, read by `tsnav claims` (ALL episodes):", ""]
            for k in checks:
                if k["diff"] is None:
                    lines.append(f"- {k['metric']}: {k['verdict']}")
                    continue
                ci = f" ± {k['ci95']:.2f}" if k.get("ci95") is not None else ""
                p = f", p = {k['p']:.3f}" if k.get("p") is not None else ""
                lines.append(
                    f"- {k['metric']}: **{k['verdict']}**; 0.7 against the best other threshold "
                    f"({k['lower_label']}): {k['diff']:+.2f}{ci}{p}"
                )
        if e.get("reading"):
            lines += ["", e["reading"]]
        lines.append("")
    return lines[:-1]


def _ci_cell(v: dict, signed: bool = False) -> str:
    lo, hi = (100 * q for q in v["ci95"])
    f = "+.2f" if signed else ".2f"
    return f"{100 * v['value']:{f}} [{lo:{f}}, {hi:{f}}]"


def levers(
    index: dict,
    results: Path,
    key: str = "levers",
    title: str = "## Levers on the pathfinding stage",
    episodes: str = "test",
) -> list[str]:
    """The lever tables (``tsnav analyze lever-table``) the index lists under ``key``, under the heading ``title``
    (each entry under its own ``title`` when it names one): per protocol, each row's SR, SPL and NSNPL and each lever's paired difference from the base row, with their
    95 % bootstrap intervals over the ``episodes`` (test, or the RoboTHOR challenge's val) episodes; an entry's own
    ``episodes`` names the list it was read on when that is another (``validation``)."""
    entries = index.get(key) or []
    if not entries:
        return []
    lines = [title, ""]
    for e in entries:
        res = json.loads((results / e["file"]).read_text())
        lines += [f"#### {e['title']}", ""] if e.get("title") else []
        lines += [
            f"{e['about']} Measured at {e['setting']}; data: [{e['file']}](results/{e['file']})"
            + (f"; validation curves: [{e['curves']}]({e['curves']})." if e.get("curves") else "."),
            "",
            *_code(e["command"]),
            "",
        ]
        for proto, t in res["protocols"].items():
            lines += [
                f"Under `{proto}`, {t['episodes']} {e.get('episodes', episodes)} episodes: value [95 % interval], and the difference from "
                f"the first row on the same episodes [paired 95 % interval], in percent.",
                "",
                "| row | SR | SPL | NSNPL | SR diff | SPL diff | NSNPL diff |",
                "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
            ]
            for r in t["rows"]:
                d = r.get("delta")
                cells = [_ci_cell(r["ALL"][m]) for m in ("SR", "SPL", "NSNPL")]
                cells += [_ci_cell(d[m], signed=True) if d else "-" for m in ("SR", "SPL", "NSNPL")]
                lines.append(f"| {r['row']} | " + " | ".join(cells) + " |")
            lines.append("")
    return lines


def metrics_table(rows: list[dict], episodes: bool = False) -> list[str]:
    """A markdown table of release-evaluation rows (``protocol``, ``policy``, ``metrics`` ALL and L>=5, and
    ``episodes`` when asked): every metric of :data:`METRICS` over all episodes, SR and SPL at L>=5, in percent."""
    ep = (" episodes |", " ---: |") if episodes else ("", "")
    lines = [
        f"| protocol | policy |{ep[0]} " + " | ".join(METRICS) + " | L>=5 SR | L>=5 SPL |",
        f"| --- | --- |{ep[1]} " + " | ".join("---:" for _ in range(len(METRICS) + 2)) + " |",
    ]
    for r in rows:
        a, b = r["metrics"]["ALL"], r["metrics"]["L>=5"]
        lines.append(
            f"| {r['protocol']} | {r['policy']} |"
            + (f" {r['episodes']} |" if episodes else "")
            + " "
            + " | ".join(_pct(a[m]) for m in METRICS)
            + f" | {_pct(b['SR'])} | {_pct(b['SPL'])} |"
        )
    return lines


def shipped_agents(cards: dict) -> list[str]:
    """One block per shipped agent: what it is, and its test figures from its card."""
    lines = [
        "## The shipped agents",
        "",
        "Each agent ships inside the package (`src/tsnav/agent/weights/NAME/`: policy, float16 encoder, model "
        "card); `tsnav release eval --agent NAME` measures it again from nothing. Figures from the cards, in "
        "percent, test episodes of Table I.",
    ]
    for name, card in cards.items():
        split = card.get("eval_split") or "test"  # a RoboTHOR agent's benchmark is the val split
        test = card.get("figures", {}).get(split, {})
        ver = f" Packed with tsnav {card['tsnav_version']}." if card.get("tsnav_version") else ""
        lines += [
            "",
            f"### `{name}`{' (default)' if card.get('default') else ''}",
            "",
            f"{card.get('summary', '')}. Detector `{card.get('detector_shipped', '?')}`; checkpoint of update "
            f"{card.get('policy_update', '?')}; model card: "
            f"[card.md](../src/tsnav/agent/weights/{name}/card.md).{ver}",
        ]
        if not test:
            lines += ["", f"No {split} figures in its card yet."]
            continue
        if split != "test":
            lines += ["", f"Its {split} figures (its benchmark: the RoboTHOR challenge's {split} episodes):"]
        lines += [""] + metrics_table(test["rows"])
    return lines


def robothor_agents(index: dict, results: Path) -> list[str]:
    """The RoboTHOR agents' ``tsnav release eval`` tables (agent, scripted explorer with the agent's detector switch,
    random; both protocols, ALL and L>=5), one per RoboTHOR agent the index's ``table1.robothor`` names."""
    lines = []
    seen = set()
    for value in (index["table1"].get("robothor") or {}).values():
        agent, rows, n = robothor_entry(value, results)
        if agent in seen:
            continue
        seen.add(agent)
        f = value if isinstance(value, str) else value["results"]
        lines += [
            f"### RoboTHOR: `{agent}` on the challenge's val episodes",
            "",
            f"`tsnav release eval --agent {agent}` ([{f}](results/{f})): greedy, 100 steps, in the 15 val "
            "apartments, which neither the agent, its detector nor its checkpoint selection ever saw; the scripted "
            "explorer switches on the agent's detector.",
            "",
        ]
        lines += metrics_table(rows, episodes=True) + [""]
    return lines


def robothor_references(index: dict, results: Path) -> list[str]:
    """RoboTHOR's scripted references (explorer, random) on the challenge's val episodes, from the file the index's
    ``table1.robothor_references`` names; nothing when it names none."""
    name = index["table1"].get("robothor_references")
    if not name:
        return []
    res = json.loads((results / name).read_text())
    lines = [
        "### RoboTHOR: the scripted references",
        "",
        f"{res['what'][0].upper()}{res['what'][1:]} ([{name}](results/{name})). Episodes kept of the "
        "challenge's 1,800: "
        + ", ".join(f"{c['kept']} under `{p}`" for p, c in res["conversion"].items())
        + " (starts off tsnav's graph, targets without a success state and, under `paper`, start-success "
        "episodes dropped and counted in the file).",
        "",
    ]
    return lines + metrics_table(res["rows"], episodes=True) + [""]


def robothor_inferred_look(index: dict, results: Path) -> list[str]:
    """What the val apartments' inferred look costs the RoboTHOR agent: its figures on train apartments built from
    their records and rebuilt the val way, from the file ``table1.robothor_inferred_look`` names."""
    name = index["table1"].get("robothor_inferred_look")
    if not name:
        return []
    res = json.loads((results / name).read_text())
    a, b = (r["metrics"]["ALL"]["SR"] for r in res["rows"][:2])
    lines = [
        "### RoboTHOR: what the val apartments' inferred look costs",
        "",
        "The val apartments have no object records: their furniture is drawn from the plans and their targets are "
        "placed from the challenge's episodes, while the train apartments the agent learns in are drawn from their "
        f"records. Rebuilt the val way, train apartments cost the shipped agent {100 * (a - b):.1f} points of SR on "
        f"their own episodes ([{name}](results/{name})): {res['what']}. {res['note']} {res.get('reading', '')}",
        "",
        *_code(res["command"]),
        "",
    ]
    return lines + metrics_table(res["rows"], episodes=True) + [""]


def robothor_switch_reach(index: dict, results: Path) -> list[str]:
    """The scripted explorer on RoboTHOR's val episodes with switches of known reach (``tsnav analyze switch-reach``),
    and the learned table's cell precision and recall, from the file ``table1.robothor_switch_reach`` names."""
    e = index["table1"].get("robothor_switch_reach")
    if not e:
        return []
    res = json.loads((results / e["file"]).read_text())
    lines = [
        "### RoboTHOR: how soon the switch must recognise the target",
        "",
        f"{e['about']} Data: [{e['file']}](results/{e['file']}).",
        "",
        *_code(e["command"]),
        "",
        "| switch | episodes | SR | SPL | SSR | never switched | L>=5 SR | L>=5 SPL |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in res["rows"]:
        a, b = r["metrics"]["ALL"], r["metrics"]["L>=5"]
        lines.append(
            f"| {r['switch']} | {r['episodes']} | {_pct(a['SR'])} | {_pct(a['SPL'])} | {_pct(a['SSR'])} | "
            f"{r['never_switched']} | {_pct(b['SR'])} | {_pct(b['SPL'])} |"
        )
    if res.get("cells"):
        lines += [
            "",
            f"`{res['table']}`'s cells (every state, each apartment's target classes):",
            "",
            f"| threshold | precision (class in the frame) | recall (cells showing >= {res['recall_pixels']} px) |",
            "| ---: | ---: | ---: |",
        ]
        lines += [f"| {c['threshold']:g} | {_pct(c['precision'])} | {_pct(c['recall'])} |" for c in res["cells"]]
    return lines + [""]


def switch_distance(index: dict, results: Path) -> list[str]:
    """Success after the stage switch by the shortest path left at the switch (``tsnav analyze agent-diagnostics
    switch-distance``), one row per evaluation, from the file the index's ``switch_distance`` names."""
    e = index.get("switch_distance")
    if not e:
        return []
    res = json.loads((results / e["file"]).read_text())
    evals = res["evaluations"]
    spans = sorted({(b["from"], b["to"]) for ev in evals for b in ev["bands"]}, key=lambda t: t[0])
    far = e.get("far_from", 15)

    def header(first: str, last: str = "") -> list[str]:
        """A band table's two header lines: ``first`` columns, one per band of ``spans``, then ``last`` if any."""
        bands = [f"{lo}-{hi - 1}" if hi is not None else f">={lo}" for lo, hi in spans]
        right = ["---:"] * (first.count("|") + len(bands) + bool(last))
        return [
            "| " + " | ".join([first, *bands] + ([last] if last else [])) + " |",
            "| --- | " + " | ".join(right) + " |",
        ]

    lines = [
        *_section_head(e),
        "Success after the switch, in percent of the switched episodes in each band of L*Nav (the shortest path "
        "left at the switch, movement actions), the band's episodes in brackets:",
        "",
        *header("evaluation | episodes | switched", f"L*Nav >= {far}: lost, % of all episodes"),
    ]

    def cells(ev: dict, cell) -> list[str]:
        """One cell per band of ``spans``: ``cell(band)`` where the evaluation has that band, else ``-``."""
        by = {(b["from"], b["to"]): b for b in ev["bands"]}
        return [cell(by[t]) if t in by else "-" for t in spans]

    for ev in evals:
        shares = cells(ev, lambda b: f"{_pct(b['success_share'])} ({b['episodes']})")
        lost = sum(b["episodes"] - b["successes"] for b in ev["bands"] if b["from"] >= far)
        lines.append(
            f"| {ev['label']} | {ev['episodes']} | {ev['switched']} | "
            + " | ".join(shares)
            + f" | {lost} ({_pct(lost / max(ev['episodes'], 1))}) |"
        )
    lines += [
        "",
        "The median LNav / L*Nav of the successes in each band (how much longer the walk after the switch was than "
        "the shortest):",
        "",
        *header("evaluation"),
    ]
    for ev in evals:
        ratios = cells(ev, lambda b: f"{b['median_ratio']:.2f}" if b["median_ratio"] is not None else "-")
        lines.append(f"| {ev['label']} | " + " | ".join(ratios) + " |")
    if all("false_switches" in b for ev in evals for b in ev["bands"]):
        lines += [
            "",
            "Of each band's switches, those made where the target was not in the frame (a false positive of the "
            "detector; ground truth read for this analysis only), their successes in brackets:",
            "",
            *header("evaluation", "all"),
        ]
        for ev in evals:
            false = cells(ev, lambda b: f"{b['false_switches']} ({b['false_successes']})")
            n = sum(b["false_switches"] for b in ev["bands"])
            won = sum(b["false_successes"] for b in ev["bands"])
            lines.append(f"| {ev['label']} | " + " | ".join(false) + f" | {n} ({won}) |")
    return lines + [""]


def pathfinding_steps(index: dict, results: Path) -> list[str]:
    """What each action after the stage switch did to the distance to the target (``tsnav analyze
    pathfinding-steps``), one row per evaluation, from the file the index's ``pathfinding_steps`` names."""
    e = index.get("pathfinding_steps")
    if not e:
        return []
    res = json.loads((results / e["file"]).read_text())["results"]
    lines = [
        *_section_head(e),
        "Per evaluation: the switched episodes and their pose actions (MoveAhead, RotateLeft, RotateRight) from the "
        "switch on, then in percent: the actions wasted (beyond the shortest walk) per pose action, the share of that "
        "waste made with the target out of the frame and in failed episodes, the pose actions taken with the target "
        "out of the frame, the MoveAheads that were blocked, and the MoveAheads with the target out of the frame that "
        "took the agent farther; last, the turns each way:",
        "",
        "| evaluation | switched | pose actions after the switch | wasted | wasted with the target out of view "
        "| wasted in failed episodes | target out of view | MoveAhead blocked | MoveAhead out of view: farther "
        "| RotateLeft / RotateRight |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]

    def total(view: dict, rows=None) -> int:
        return sum(
            n for k, row in view.items() if k != "LookUp/LookDown" and (rows is None or k in rows) for n in row.values()
        )

    for r in res:
        c, w = r["counts"], r["wasted"]
        pose = total(c["in view"]) + total(c["out of view"])
        wasted = w["in view"] + w["out of view"]
        moves = {k: c["in view"]["MoveAhead"][k] + c["out of view"]["MoveAhead"][k] for k in c["in view"]["MoveAhead"]}
        away = c["out of view"]["MoveAhead"]
        turns = [total(c["in view"], (a,)) + total(c["out of view"], (a,)) for a in ("RotateLeft", "RotateRight")]
        lines.append(
            f"| {r['label']} | {r['episodes']} | {pose} | {_pct(wasted / max(pose, 1))} "
            f"| {_pct(w['out of view'] / max(wasted, 1))} | {_pct(r['wasted_failures'] / max(wasted, 1))} "
            f"| {_pct(total(c['out of view']) / max(pose, 1))} | {_pct(moves['blocked'] / max(sum(moves.values()), 1))} "
            f"| {_pct(away['farther'] / max(sum(away.values()), 1))} | {turns[0]} / {turns[1]} |"
        )
    return lines + ["", e.get("reading", ""), ""] if e.get("reading") else lines + [""]


def render(root: Path | None = None, weights: Path = WEIGHTS) -> str:
    """The whole page, from ``root/docs/results`` (index and result files), the cards under ``weights`` and the
    paper's figures."""
    root = Path(root) if root else repo_root()
    results = root / "docs" / "results"
    index = json.loads((results / "index.json").read_text())
    paper = published_figures()
    cards = read_cards(weights)
    lines = [
        "# Results",
        "",
        "<!-- generated by `python -m tsnav.report.results_page` from docs/results/index.json, the result files "
        "it names and the shipped agents' model cards; do not edit by hand -->",
        "",
        "The paper's tables with tsnav's measured figures beside the published ones. tsnav's figures come from "
        "its embedded world (the real iTHOR rooms rebuilt from their recorded layouts, no Unity) on a CPU, with "
        "smaller networks and budgets than the paper's GPU runs; each table says how it was made.",
        "",
        PROTOCOL_SENTENCE,
        "",
        "How every figure here was reached, with the runs that led to them and the settings since replaced: "
        "[the results notebook](history/RESULTS.md). Speed: [BENCHMARKS.md](../BENCHMARKS.md).",
        "",
    ]
    lines += table1(index, cards, paper, results) + [""]
    lines += robothor_agents(index, results)
    lines += robothor_references(index, results)
    lines += robothor_switch_reach(index, results)
    lines += robothor_inferred_look(index, results)
    lines += levers(index, results, "robothor_levers", "### RoboTHOR: levers on the column", "val")
    lines += experiment_table(
        "Table II: ablation of the two rewards and DE-MAE", "table2", index.get("table2", []), paper, results
    ) + [""]
    lines += experiment_table(
        "Table III: pretraining methods (baseline reward)", "table3", index.get("table3", []), paper, results
    ) + [""]
    lines += switch_distance(index, results)
    lines += pathfinding_steps(index, results)
    lines += levers(index, results)
    lines += fig4(index, results) + [""]
    lines += shipped_agents(cards)
    return "\n".join(lines) + "\n"


#: The README's copy of Table I (the index's ``readme`` selection) sits between these two lines.
README_BEGIN = "<!-- Table I: rendered by `python -m tsnav.report.results_page`; do not edit by hand -->"
README_END = "<!-- end of Table I -->"


def readme_table(root: Path | None = None, weights: Path = WEIGHTS) -> str:
    """The README's short Table I: the rows the index's ``readme`` entry names."""
    root = Path(root) if root else repo_root()
    index = json.loads((root / "docs" / "results" / "index.json").read_text())
    return "\n".join(
        table1_rows(
            index, read_cards(weights), published_figures(), select=index["readme"], results=root / "docs" / "results"
        )
    )


def with_readme_table(readme: str, table: str) -> str:
    """``readme`` with the text between :data:`README_BEGIN` and :data:`README_END` replaced by ``table``."""
    if README_BEGIN not in readme or README_END not in readme:
        raise ValueError(f"README.md has no Table I block (the lines {README_BEGIN!r} ... {README_END!r})")
    head, rest = readme.split(README_BEGIN, 1)
    _, tail = rest.split(README_END, 1)
    return f"{head}{README_BEGIN}\n{table}\n{README_END}{tail}"


def pages(root: Path) -> dict[Path, str]:
    """Every file this module renders, path -> text: docs/RESULTS.md and README.md with its Table I."""
    readme = root / "README.md"
    return {
        root / "docs" / "RESULTS.md": render(root),
        readme: with_readme_table(readme.read_text(), readme_table(root)),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, prog="python -m tsnav.report.results_page", description=__doc__.splitlines()[0]
    )
    p.add_argument("--root", default=None, help="the checkout (default: the one this module runs from)")
    p.add_argument("--check", action="store_true", help="write nothing; exit 1 when a page is stale")
    args = p.parse_args(argv)
    root = Path(args.root) if args.root else repo_root()
    stale = []
    for out, text in pages(root).items():
        if args.check:
            if not out.exists() or out.read_text() != text:
                stale.append(out)
            continue
        atomic_write_text(out, text)
        print(f"wrote {out} ({text.count(chr(10))} lines)")
    if stale:
        print(f"stale: {', '.join(map(str, stale))}; run python -m tsnav.report.results_page", file=sys.stderr)
        return 1
    if args.check:
        print("docs/RESULTS.md and README.md's Table I are up to date")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
