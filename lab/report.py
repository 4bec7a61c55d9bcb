"""The tables' text: each table's markdown beside the paper's numbers, its claims judged by the
paired t-test (claim_test) and written one line each, the breakdowns under it, and the report of a
run. experiments.py hands its results over to it; nothing here makes a number the tables hold."""

from __future__ import annotations

import math
import pathlib
import statistics
import time

import torch

from lab import waymo
import data_synth
from lab.cli import machine
from lab.runs import write_atomic
from specs import (
    CLOSE,
    CURVE_SAMPLES,
    RELATIVE_SCALE,
    SPECS,
    Claim,
    TableSpec,
)
from lab.stats import (
    PairedDifference,
    cell,
    claim_verdict,
    markdown_table,
    mean_se,
    p_value,
    paired_difference,
    plus_minus,
)


def gap_closed(
    results: dict, standard="Standard", diffstack="DiffStack", metric="rel_hindsight"
) -> tuple:
    """Share of the Standard -> GT prediction gap that DiffStack closes, seed by seed: mean and s.e.
    over the seeds where there is a gap; (nan, nan) where Standard is as good as GT prediction in
    every seed (a few scenarios)."""
    gt = results["GT prediction"][0][metric]
    pairs = [
        (s[metric], d[metric])
        for s, d in zip(results[standard], results[diffstack])
        if metric in s and metric in d and s[metric] != gt  # (a diverged seed has no metrics)
    ]
    return mean_se([(s - d) / (s - gt) for s, d in pairs]) if pairs else (math.nan, math.nan)


def claim_test(claim: Claim, spec: TableSpec, results: dict) -> tuple:
    """(the claim's Column, the PairedDifference of its rows over the seeds, or None where no seed
    has both: they diverged); results: those its rows are in."""
    col = next((c for c in spec.columns if c.header == claim.column), None)
    if col is None:
        raise ValueError(f"claim.column: {claim.column!r} is not a column of {spec.name}")
    # (a baseline without a predictor to train has one run: it pairs with every seed)
    base = results[claim.baseline]
    base = base * len(results[claim.method]) if len(base) == 1 else base
    # seed by seed; a diverged one is left out
    pairs = [
        (b[0], m[0])
        for b, m in (
            (col.values([rb]), col.values([rm])) for rb, rm in zip(base, results[claim.method])
        )
        if b and m
    ]
    if not pairs:  # every seed of one row or the other diverged
        return col, None
    return col, paired_difference([b for b, _ in pairs], [m for _, m in pairs])


def claim_line(claim: Claim, spec: TableSpec, results: dict) -> str:
    """A claim's line (results: those its rows are in): the paired difference (method - baseline),
    t, the seeds, the verdict."""
    col, p = claim_test(claim, spec, results)
    name = (
        claim.column[0].lower() + claim.column[1:] if claim.column[1:2].islower() else claim.column
    )
    where = f"{claim.section}: " if claim.section else ""
    diverged = sum("diverged" in r for r in results[claim.baseline] + results[claim.method])
    if p is None:
        return (
            f"{where}{claim.method} vs {claim.baseline}, {name}: untested (no seed trained both "
            f"rows; {diverged} diverged)"
        )
    t = (
        f"t = {p.t:.2f}, {p_value(p.p)}"
        if math.isfinite(p.t)
        else ("no spread over seeds" if p.se == 0 else "one seed")
    )
    seeds = (
        f"{p.better} of {p.n} seeds better" + (f", {p.worse} worse" if p.worse else "")
        if claim.direction < 0
        else f"{p.worse} of {p.n} seeds higher" + (f", {p.better} lower" if p.better else "")
    )
    seeds += f"; {diverged} diverged, left out" if diverged else ""
    return (
        f"{where}{claim.method} vs {claim.baseline}, {name}: paired difference "
        f"{plus_minus(col.fmt, p.mean, p.se)} ({t}, {seeds}): "
        f"{claim_verdict(p, claim.direction)}"
    )


def claims_markdown(spec: TableSpec, results: dict) -> str:
    """The claim lines of a table, a markdown list; '' when it makes no claim (or its rows were
    not run)."""

    def runs(c):  # the results the claim's rows are in: the table's, or its ablation section's
        return results.get(c.section, {}) if c.section else results

    lines = [
        claim_line(c, spec, runs(c))
        for c in spec.claims
        if c.method in runs(c) and c.baseline in runs(c)
    ]
    return "\n".join(f"- {line}" for line in lines)


def claims_card(tables: dict) -> str:
    """The paper against this run, one row per claim of the paper: tables {table name: its results}.
    The paper's and our values of the two rows (means over seeds), the paired test and its verdict
    (claim_line's)."""
    rows = []
    for name, results in tables.items():
        spec = SPECS[name]
        for c in spec.claims:
            runs = results.get(c.section, {}) if c.section else results
            if c.method not in runs or c.baseline not in runs:
                continue
            col, p = claim_test(c, spec, runs)
            if p is None:  # every seed of a row diverged: nothing to pair
                p = PairedDifference(math.nan, math.nan, math.nan, math.nan, 0, 0, 0)
            paper = spec.paper.get(c.section, {}) if c.section else spec.paper
            was = [paper.get(row, {}).get(col.header) for row in (c.method, c.baseline)]
            ours = [
                statistics.fmean(v) if (v := col.values(runs[row])) else math.nan
                for row in (c.method, c.baseline)
            ]
            test = f"t = {p.t:.2f}, {p_value(p.p)}" if math.isfinite(p.t) else "--"
            rows.append(
                [
                    spec.title.split(":")[0] + (f" ({c.section})" if c.section else ""),
                    f"{c.method} {'<' if c.direction < 0 else '>'} {c.baseline}, {col.header}",
                    " vs ".join("--" if v is None else col.fmt.format(v) for v in was),
                    " vs ".join("--" if math.isnan(v) else col.fmt.format(v) for v in ours),
                    "--" if p.n == 0 else plus_minus(col.fmt, p.mean, p.se),
                    test,
                    claim_verdict(p, c.direction),
                ]
            )
    return markdown_table(
        ["Table", "Claim", "Paper", "Here (mean)", "Paired difference", "Test", "Verdict"], rows
    )


def ablation_markdown(spec: TableSpec, results: dict) -> str:
    """The ablation table: the loss multipliers (x1, x1e2, x1e3 as in the paper), ADE, NLL and the
    planning metrics relative to the section's No prediction (x1e-2); '--' where a loss or metric
    does not apply."""
    head = ["Method", "L_pred x1", "L_plan x1e2", "L_ctr x1e3"] + [c.header for c in spec.columns]
    rows = []
    for title, stack_kw, methods in spec.sections:
        if title not in results:
            continue
        rows.append([f"**{title}**"] + [""] * (len(head) - 1))
        no_plan, no_ctrl = stack_kw.get("planner") is False, stack_kw.get("controller") is False
        for name, runs in results[title].items():
            m = next((m for m in methods if m.name == name), None)
            loss = ["", "", ""] if m is None else [f"{v:g}" for v in m.losses]
            loss[1:] = ["--" if no_plan else loss[1], "--" if no_ctrl else loss[2]]
            cells = [cell(c.values(runs), c.fmt, name) for c in spec.columns]
            cells[2] = "--" if no_plan else cells[2]
            rows.append([name, *loss, *cells])
    return markdown_table(head, rows)


def goal_markdown(results: dict) -> str:
    """The goal table: per goal, per behaviour, No prediction's hindsight cost and what it is made
    of, and what a perfect prediction saves (GT prediction minus No prediction, x1e-2, and its share
    of the whole saving)."""
    parts = []
    for goal, rows in results.items():
        none, gt = rows["No prediction"][0], rows["GT prediction"][0]
        saved_all = (gt["hindsight"] - none["hindsight"]) * none["n"]
        table = []
        for b in [b for b in data_synth.BEHAVIOURS if b in none["by_behaviour"]]:
            a, g = none["by_behaviour"][b], gt["by_behaviour"][b]
            t = a["terms"]
            saved = g["hindsight"] - a["hindsight"]
            table.append(
                [
                    f"{b} ({a['n']})",
                    f"{a['hindsight']:.3f}",
                    f"{t[0]:.3f}",
                    f"{t[1]:.3f}",
                    f"{t[4]:.3f}",
                    f"{g['terms'][0]:.3f}",
                    f"{100 * a['close']:.0f} % / {100 * g['close']:.0f} %",
                    f"{saved / 1e-2:+.2f}",
                    f"{saved * a['n'] / saved_all:.2f}" if saved_all else "--",
                ]
            )
        table.append(
            [
                f"all ({none['n']})",
                f"{none['hindsight']:.3f}",
                "",
                "",
                "",
                "",
                "",
                f"{(gt['hindsight'] - none['hindsight']) / 1e-2:+.2f}",
                "1.00",
            ]
        )
        what = (
            "the paper's: the GT ego state at T"
            if goal == "logged"
            else "a route goal: where the ego would be at T keeping its speed along its lane "
            "(Config.goal = 'route')"
        )
        parts.append(
            f"**Goal: {what}.**\n\n"
            + markdown_table(
                [
                    "Behaviour (scenes)",
                    "No prediction: hindsight cost",
                    "of which collision",
                    "goal",
                    "control effort",
                    "GT prediction: collision",
                    f"within {CLOSE:g} m of the vehicle (No prediction / GT)",
                    "GT minus No prediction (x1e-2)",
                    "share of GT's saving",
                ],
                table,
            )
        )
    return "\n\n".join(parts)


def results_markdown(spec: TableSpec, results: dict) -> str:
    """A spec's results table ('mean ± s.e.' over seeds), then its claim lines (claims_markdown),
    the diverged trainings, the breakdown by behaviour (open loop) and the learning curves' plateau
    (Table 1)."""
    if spec.kind == "goal":
        return goal_markdown(results)
    md = (
        ablation_markdown(spec, results)
        if spec.kind == "ablation"
        else table_markdown(spec, results)
    )
    claims = claims_markdown(spec, results)
    md += (
        "\n\nThe paper's claims, as paired differences over seeds (a two-sided paired t-test; "
        f"reproduced only at p < 0.05 in the paper's direction):\n\n{claims}"
        if claims
        else ""
    )
    by = behaviour_markdown(spec, results) if spec.kind == "open_loop" else ""
    curves = plateau_markdown(results) if "learning_curves.png" in spec.figures else ""
    return md + "".join(f"\n\n{part}" for part in (diverged_markdown(results), by, curves) if part)


def diverged_markdown(results: dict) -> str:
    """One line per training that diverged (its seed is left out of the means and the paired
    differences)."""
    found = []
    stack = [results]
    while stack:  # tables nest {method: [runs]} in sections, and Table 3 has {row: [runs]}
        item = stack.pop()
        for v in item.values() if isinstance(item, dict) else item:
            if isinstance(v, dict) and "diverged" in v:
                found.append(v["diverged"])
            elif isinstance(v, (dict, list)):
                stack.append(v)
    return "Diverged, left out of the means: " + "; ".join(sorted(set(found))) if found else ""


def behaviour_markdown(spec: TableSpec, results: dict) -> str:
    """The setting's planning metric (RL: hindsight cost, IL: MSE) relative to No prediction per
    behaviour of the predicted vehicle, as the table below says: where a method's predictions help
    the planner and where they hurt it. '' without the breakdown (real data, or results from before
    it existed)."""
    key = "hindsight" if spec.setting == "rl" else "mse"
    base = results.get("No prediction", [{}])[0].get("by_behaviour")
    if not base:
        return ""
    methods = [
        m
        for m, runs in results.items()
        if m != "No prediction" and all("by_behaviour" in r for r in runs)
    ]
    rows = []
    for b in [b for b in data_synth.BEHAVIOURS if b in base]:

        def rel(runs):
            return [(r["by_behaviour"][b][key] - base[b][key]) / 1e-2 for r in runs]

        rows.append([f"{b} ({base[b]['n']})"] + [cell(rel(results[m]), row=m) for m in methods])
    rows.append(
        [f"all ({results['No prediction'][0]['n']})"]
        + [
            cell([(r[key] - results["No prediction"][0][key]) / 1e-2 for r in results[m]], row=m)
            for m in methods
        ]
    )
    what = "Hindsight cost" if key == "hindsight" else "MSE"
    return (
        f"{what} relative to No prediction (x1e-2) by behaviour of the predicted vehicle "
        "(scenes), mean ± s.e. over seeds; a behaviour's row is the mean over its scenes, 'all' "
        "over every scene:\n\n" + markdown_table(["Behaviour (scenes)"] + methods, rows)
    )


def has_curves(results: dict) -> bool:
    """Whether a table's results carry learning curves (runs from before they existed do not)."""
    return any(r.get("curve") for runs in results.values() if isinstance(runs, list) for r in runs)


def plateau_markdown(results: dict, methods=("Standard", "DiffStack"), last: float = 5.0) -> str:
    """Whether training has flattened: per method, the change of ADE and hindsight cost over the
    last `last` epochs of the curves, mean ± s.e.: 'still falling' past 2 s.e. and 1 % of the value,
    else 'flat' ('' without curves)."""
    lines = []
    for m in methods:
        curves = [r["curve"] for r in results.get(m, []) if r.get("curve")]
        if not curves:
            continue
        parts = []
        for key, unit in (("ade", " m"), ("hindsight", "")):
            end = [c[-1][key] for c in curves]
            before = [
                min(c, key=lambda e: abs(e["epoch"] - (c[-1]["epoch"] - last)))[key] for c in curves
            ]
            mean, se = mean_se([a - b for a, b in zip(end, before)])
            # (one seed: no s.e., the 1 % alone decides)
            falling = not mean >= -2 * se and mean < -0.01 * abs(statistics.fmean(end))
            parts.append(
                f"{'ADE' if key == 'ade' else 'hindsight cost'} "
                f"{plus_minus('{:+.3f}', mean, se).replace('± +', '± ')}{unit} "
                f"({'still falling' if falling else 'flat'})"
            )
        # its scenes: those evaluated and those skipped (CURVE_SAMPLES, or fewer in a small run)
        final = curves[0][-1]
        scenes = final.get("n", CURVE_SAMPLES) + final.get("skipped", 0)
        lines.append(
            f"- {m}, over the last {min(last, final['epoch']):g} of {final['epoch']:g} epochs "
            f"({len(curves)} seeds, {scenes} validation scenes): " + "; ".join(parts)
        )
    return "Learning curves (learning_curves.png):\n\n" + "\n".join(lines) if lines else ""


def table_markdown(spec: TableSpec, results: dict) -> str:
    """The table of a non-ablation spec, with the gap closed and the closed loop's absolute baseline
    below it."""
    rows = [
        [name] + [cell(c.values(runs), c.fmt, name) for c in spec.columns]
        for name, runs in results.items()
    ]
    md = markdown_table(["Method"] + [c.header for c in spec.columns], rows)
    trained = [any("rel_hindsight" in r for r in results.get(row, [])) for row in (spec.gap or ())]
    if spec.gap and not all(trained):
        md += f"\n\nNo gap closed is given: every seed of {' or '.join(spec.gap)} diverged."
    elif spec.gap:
        m, s = gap_closed(results, *spec.gap)
        md += (
            f"\n\n{spec.gap[1]} closes {plus_minus('{:.0f}', 100 * m, 100 * s)} % of the "
            f"{spec.gap[0]} -> "
            "GT prediction hindsight-cost gap."
            if math.isfinite(m)
            else f"\n\n{spec.gap[0]} is as good as GT prediction here: there is no gap to close."
        )
    if spec.kind == "closed_loop":
        base = results["No prediction"][0]
        md += (
            f"\n\nNo prediction, absolute: trajectory cost {base['trajectory']:.4f}, open-loop "
            f"cost {base['open_loop']:.4f}, deviation {base['deviation']:.3f} m "
            f"({base['scenes']} scenes)."
        )
    return md


def paper_markdown(spec: TableSpec) -> str:
    """The paper's numbers for the same columns ('--': not reported)."""

    def rows(paper):
        return [
            [name]
            + [
                ("{:.2f}".format(vals[c.header]) if c.header in vals else "--")
                for c in spec.columns
            ]
            for name, vals in paper.items()
        ]

    head = ["Method (paper)"] + [c.header for c in spec.columns]
    if spec.kind == "ablation":
        return "\n\n".join(
            markdown_table([f"{t} (paper)"] + head[1:], rows(paper))
            for t, paper in spec.paper.items()
        )
    return markdown_table(head, rows(spec.paper))


def write_report(out_dir, sections, metas=(), rendered=False, tables=None) -> pathlib.Path:
    """out_dir/report.md: sections, a list of (title, markdown, [figure files in out_dir]), each
    figure linked below its section, after the paper-vs-here card of tables {name: results}
    (claims_card). Its first line says when, where and on which device the tables were made, from
    their metas, and when it was re-rendered from them (--render); without metas, this process's
    date and machine."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if metas:
        dates = sorted({m["date"] for m in metas})
        when = dates[0] if len(dates) == 1 else f"{dates[0]} to {dates[-1]}"
        header = (
            f"Tables made {when} on {'; '.join(dict.fromkeys(m['machine'] for m in metas))}, "
            f"device {', '.join(dict.fromkeys(m.get('device', 'cpu') for m in metas))}"
        )
        if any(m.get("computed_on") for m in metas):  # a run resumed on other machines
            header += " (pieces computed on several machines: see the sections)"
        header += (
            f" (rendered {time.strftime('%Y-%m-%d')} from their JSON files)" if rendered else ""
        )
    else:
        header = (
            f"{time.strftime('%Y-%m-%d')}, {machine()}, torch {torch.__version__}, "
            f"{torch.get_num_threads()} threads"
        )
    parts = [f"# DiffStack: results\n\n{header}\n"]
    if tables:
        parts += [
            "## The paper's claims, here\n\nEach claim is a two-sided paired t-test over the "
            "seeds; reproduced only at p < 0.05 in the paper's "
            f"direction.\n\n{claims_card(tables)}\n"
        ]
    for title, md, files in sections:
        parts += [f"## {title}\n\n{md}\n"] + [f"![{f}]({f})\n" for f in files]
    write_atomic(out / "report.md", "\n".join(parts))
    return out / "report.md"


def section_markdown(spec: TableSpec, meta: dict, table: str) -> str:
    """A table's provenance line (its command, date, machine, device, seconds, commit, and a note if
    the run has one), the table, and the paper's numbers: the text of its .md file and of its
    section of the report."""
    where = [meta["date"], meta["machine"]] + (
        [f"device {meta['device']}"] if "device" in meta else []
    )
    where += [f"{meta['seconds']:.0f} s"]
    # a resumed run's own seconds are only what was left; workers overlap
    if "piece_seconds" in meta:
        where[-1] += (
            f" wall in this command, {meta['piece_seconds']:.0f} s of computing summed over its "
            f"{meta['pieces']} pieces ({meta['piece_cpu_seconds']:.0f} CPU s)"
        )
    where += [f"commit {meta['git_commit']}"] if meta.get("git_commit") else []
    note = f"; {meta['note']}" if meta.get("note") else ""
    # a resumed run's pieces from several machines: the same seed differs between them
    if meta.get("computed_on"):
        where_ran = ", ".join(
            f"{m} ({k} piece{'s' * (k > 1)})" for m, k in meta["computed_on"].items()
        )
        note += (
            f"; its pieces ran on {len(meta['computed_on'])} machines, and the same seed gives "
            f"other numbers on another kind of processor: {where_ran}"
        )
    return f"`{meta['command']}` ({', '.join(where)}{note})\n\n{table}\n\n" + (
        f"The paper's numbers:\n\n{paper_markdown(spec)}\n"
        if spec.paper
        else f"{waymo.WAYMO_LICENCE}.\n"
        if spec.kind == "real"
        else ""
    )


def table_file_markdown(spec: TableSpec, md: str) -> str:
    """out_dir/<name>.md: the title, section_markdown's text and links to the table's figures."""
    return f"# {spec.title}\n\n{md}" + "".join(f"\n![{f}]({f})\n" for f in spec.figures)


def open_loop_table(results: dict, setting="rl") -> str:
    """Tables 1, 2 and 4's columns for {method: [per-seed metrics]}: ADE, NLL, the planning metrics
    relative to No prediction, iLQR's convergence; means ± standard errors over seeds."""
    rel = {"plan_loss": "Planning loss", "hindsight": "Hindsight cost", "mse": "MSE"}
    scales = RELATIVE_SCALE[setting]
    head = ["Method", "ADE (m)", "NLL (nats)"] + [
        f"{rel[k]} (x{v:.0e})".replace("e-0", "e-") for k, v in scales.items()
    ]
    rows = []
    for name, runs in results.items():

        def get(key):
            return [r[key] for r in runs] if key in runs[0] else []

        rows.append(
            [name, cell(get("ade"), row=name), cell(get("nll"), row=name)]
            + [cell(get("rel_" + k), row=name) for k in scales]
            + [cell(get("converged"), "{:.3f}", name)]
        )
    return markdown_table(head + ["iLQR converged"], rows)
