"""The tables' text: each table's markdown beside the paper's numbers, its claims judged by the
paired t-test, the breakdowns, the report of a run (what they show: docs/results.md)."""

import math
import pathlib
import statistics
import time

import torch

from lab import waymo
import data_synth
from diffstack import COST_TERMS
from lab.cli import machine
from lab.runs import write_atomic
from specs import CLOSE, SPECS, Claim, TableSpec, open_loop_columns
from lab.stats import PairedDifference, cell, claim_verdict, markdown_table, mean_se
from lab.stats import p_value, paired_difference, plus_minus


def gap_closed(results: dict, standard="Standard", diffstack="DiffStack") -> tuple:
    """The share of the Standard -> GT prediction gap DiffStack closes: mean, s.e. (nan: no gap)."""
    key = "rel_hindsight"
    gt = results["GT prediction"][0][key]
    pairs = [
        (s[key], d[key])
        for s, d in zip(results[standard], results[diffstack])
        if key in s and key in d and s[key] != gt  # (a diverged seed has no metrics)
    ]
    return mean_se([(s - d) / (s - gt) for s, d in pairs]) if pairs else (math.nan, math.nan)


def claim_test(claim: Claim, spec: TableSpec, results: dict) -> tuple:
    """(the claim's Column, the PairedDifference of its rows, or None where no seed has both)."""
    col = next((c for c in spec.columns if c.header == claim.column), None)
    if col is None:
        raise ValueError(f"claim.column: {claim.column!r} is not a column of {spec.name}")
    # (a baseline without a predictor to train has one run: it pairs with every seed)
    base = results[claim.baseline]
    base = base * len(results[claim.method]) if len(base) == 1 else base
    values = [(col.values([rb]), col.values([rm])) for rb, rm in zip(base, results[claim.method])]
    pairs = [(b[0], m[0]) for b, m in values if b and m]  # seed by seed; a diverged one left out
    if not pairs:  # every seed of one row or the other diverged
        return col, None
    return col, paired_difference([b for b, _ in pairs], [m for _, m in pairs])


def claims_of(spec: TableSpec, results: dict):
    """(claim, the results its rows are in) for each claim whose two rows were run."""
    for c in spec.claims:
        runs = results.get(c.section, {}) if c.section else results
        if c.method in runs and c.baseline in runs:
            yield c, runs


def t_test(p: PairedDifference) -> str | None:
    """'t = .., p = ..'; None without one (one seed, no spread)."""
    return f"t = {p.t:.2f}, {p_value(p.p)}" if math.isfinite(p.t) else None


def claim_line(claim: Claim, spec: TableSpec, results: dict) -> str:
    """The paired difference (method - baseline), t, the seeds, the verdict."""
    col, p = claim_test(claim, spec, results)
    c = claim.column
    name = c[0].lower() + c[1:] if c[1:2].islower() else c  # 'hindsight cost', 'MSE'
    where = f"{claim.section}: " if claim.section else ""
    what = f"{where}{claim.method} vs {claim.baseline}, {name}"
    diverged = sum("diverged" in r for r in results[claim.baseline] + results[claim.method])
    if p is None:
        return f"{what}: untested (no seed trained both rows; {diverged} diverged)"
    t = t_test(p) or ("no spread over seeds" if p.se == 0 else "one seed")
    seeds = (
        f"{p.better} of {p.n} seeds better" + (f", {p.worse} worse" if p.worse else "")
        if claim.direction < 0
        else f"{p.worse} of {p.n} seeds higher" + (f", {p.better} lower" if p.better else "")
    )
    seeds += f"; {diverged} diverged, left out" if diverged else ""
    diff = plus_minus(col.fmt, p.mean, p.se)
    return f"{what}: paired difference {diff} ({t}, {seeds}): {claim_verdict(p, claim.direction)}"


def claims_markdown(spec: TableSpec, results: dict) -> str:
    """The claim lines of a table, a markdown list; '' for none."""
    return "\n".join(f"- {claim_line(c, spec, runs)}" for c, runs in claims_of(spec, results))


def claims_card(tables: dict) -> str:
    """One row per claim of tables {name: results}: paper vs here, the paired test, the verdict."""
    rows = []
    for name, results in tables.items():
        spec = SPECS[name]
        for c, runs in claims_of(spec, results):
            col, p = claim_test(c, spec, runs)
            if p is None:  # nothing to pair
                p = PairedDifference(math.nan, math.nan, math.nan, math.nan, 0, 0, 0)
            paper = spec.paper.get(c.section, {}) if c.section else spec.paper
            two = (c.method, c.baseline)
            was = [paper.get(row, {}).get(col.header) for row in two]
            ours = [statistics.fmean(v) if (v := col.values(runs[row])) else None for row in two]
            vs = [
                " vs ".join("--" if v is None else col.fmt.format(v) for v in x)
                for x in (was, ours)
            ]
            table = spec.title.split(":")[0] + (f" ({c.section})" if c.section else "")
            claim = f"{c.method} {'<' if c.direction < 0 else '>'} {c.baseline}, {col.header}"
            diff = "--" if p.n == 0 else plus_minus(col.fmt, p.mean, p.se)
            rows.append([table, claim, *vs, diff, t_test(p) or "--", claim_verdict(p, c.direction)])
    head = ["Table", "Claim", "Paper", "Here (mean)", "Paired difference", "Test", "Verdict"]
    return markdown_table(head, rows)


def ablation_markdown(spec: TableSpec, results: dict) -> str:
    """The ablation table per section: loss multipliers and columns ('--': does not apply)."""
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
    """Per goal and behaviour: No prediction's hindsight cost and terms, and GT's saving."""
    head = ["Behaviour (scenes)", "No prediction: hindsight cost", "of which collision", "goal"]
    head += ["control effort", "GT prediction: collision"]
    head += [f"within {CLOSE:g} m of the vehicle (No prediction / GT)"]
    head += ["GT minus No prediction (x1e-2)", "share of GT's saving"]
    parts, i_coll = [], COST_TERMS.index("coll")
    for goal, rows in results.items():
        none, gt = rows["No prediction"][0], rows["GT prediction"][0]
        saved_all = (gt["hindsight"] - none["hindsight"]) * none["n"]
        table = []
        for b in [b for b in data_synth.BEHAVIOURS if b in none["by_behaviour"]]:
            a, g = none["by_behaviour"][b], gt["by_behaviour"][b]
            saved = g["hindsight"] - a["hindsight"]
            of = dict(zip(COST_TERMS, a["terms"]))  # eq. (3)'s terms, by name
            costs = [a["hindsight"], of["coll"], of["goal"], of["ctrl"], g["terms"][i_coll]]
            close = f"{100 * a['close']:.0f} % / {100 * g['close']:.0f} %"
            share = f"{saved * a['n'] / saved_all:.2f}" if saved_all else "--"
            gain = f"{saved / 1e-2:+.2f}"
            table.append([f"{b} ({a['n']})", *(f"{v:.3f}" for v in costs), close, gain, share])
        saved = f"{(gt['hindsight'] - none['hindsight']) / 1e-2:+.2f}"
        table.append([f"all ({none['n']})", f"{none['hindsight']:.3f}", *[""] * 5, saved, "1.00"])
        parts.append(f"**Goal: {goal}**\n\n" + markdown_table(head, table))
    return "\n\n".join(parts)


def results_markdown(spec: TableSpec, results: dict) -> str:
    """A spec's table, its claims, what diverged and (open loop) the breakdown by behaviour."""
    if spec.kind == "goal":
        return goal_markdown(results)
    table = ablation_markdown if spec.kind == "ablation" else table_markdown
    claims = claims_markdown(spec, results)
    claims = claims and f"The paper's claims, paired t-test over seeds:\n\n{claims}"
    by = behaviour_markdown(spec, results) if spec.kind == "open_loop" else ""
    parts = (table(spec, results), claims, diverged_markdown(results), by)
    return "\n\n".join(part for part in parts if part)


def diverged_markdown(results: dict) -> str:
    """The trainings that diverged, anywhere in results, one line."""
    found, stack = set(), [results]
    while stack:
        item = stack.pop()
        found |= {item["diverged"]} if isinstance(item, dict) and "diverged" in item else set()
        stack += item.values() if isinstance(item, dict) else item if isinstance(item, list) else []
    return "Diverged, left out of the means: " + "; ".join(sorted(found)) if found else ""


def behaviour_markdown(spec: TableSpec, results: dict) -> str:
    """RL's hindsight cost or IL's MSE relative to No prediction per behaviour; '' without one."""
    key = "hindsight" if spec.setting == "rl" else "mse"
    none = results.get("No prediction", [{}])[0]
    if not none.get("by_behaviour"):
        return ""
    methods = [m for m in results if m != "No prediction"]
    methods = [m for m in methods if all("by_behaviour" in r for r in results[m])]
    rows = []
    for b in [b for b in data_synth.BEHAVIOURS if b in none["by_behaviour"]] + ["all"]:

        def part(r):  # a run's numbers over behaviour b's scenes, or over every scene
            return r if b == "all" else r["by_behaviour"][b]

        rel = {m: [(part(r)[key] - part(none)[key]) / 1e-2 for r in results[m]] for m in methods}
        rows.append([f"{b} ({part(none)['n']})"] + [cell(rel[m], row=m) for m in methods])
    what = "Hindsight cost" if key == "hindsight" else "MSE"
    return (
        f"{what} relative to No prediction (x1e-2) by behaviour of the predicted vehicle:\n\n"
        + markdown_table(["Behaviour (scenes)"] + methods, rows)
    )


def has_curves(results: dict) -> bool:
    """Whether results carry learning curves (runs from before they existed do not)."""
    return any(r.get("curve") for runs in results.values() if isinstance(runs, list) for r in runs)


def method_table(columns, results: dict) -> str:
    """One row per method of {method: [per-seed metrics]}, a cell per column."""
    rows = [
        [name] + [cell(c.values(runs), c.fmt, name) for c in columns]
        for name, runs in results.items()
    ]
    return markdown_table(["Method"] + [c.header for c in columns], rows)


def open_loop_table(results: dict, setting="rl") -> str:
    """Tables 1, 2 and 4's columns (specs.open_loop_columns) for {method: [per-seed metrics]}."""
    return method_table(open_loop_columns(setting), results)


def table_markdown(spec: TableSpec, results: dict) -> str:
    """A table, the gap closed and the closed loop's absolute baseline below."""
    md = method_table(spec.columns, results)
    trained = [any("rel_hindsight" in r for r in results.get(row, [])) for row in (spec.gap or ())]
    if spec.gap and not all(trained):
        md += f"\n\nNo gap closed is given: every seed of {' or '.join(spec.gap)} diverged."
    elif spec.gap:
        m, s = gap_closed(results, *spec.gap)
        md += (
            f"\n\n{spec.gap[1]} closes {plus_minus('{:.0f}', 100 * m, 100 * s)} % of the "
            f"{spec.gap[0]} -> GT prediction hindsight-cost gap."
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

    def table(first, paper):
        rows = [
            [name] + [f"{vals[c.header]:.2f}" if c.header in vals else "--" for c in spec.columns]
            for name, vals in paper.items()
        ]
        return markdown_table([first] + [c.header for c in spec.columns], rows)

    if spec.kind == "ablation":
        return "\n\n".join(table(f"{t} (paper)", paper) for t, paper in spec.paper.items())
    return table("Method (paper)", spec.paper)


def write_report(out_dir, sections, metas=(), rendered=False, tables=None) -> pathlib.Path:
    """out_dir/report.md: the claims card of tables {name: results}, then sections [(title, md,
    [figures])], under when and where the tables were made (metas) and rendered."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if metas:
        dates = sorted({m["date"] for m in metas})
        when = dates[0] if len(dates) == 1 else f"{dates[0]} to {dates[-1]}"
        machines = "; ".join(dict.fromkeys(m["machine"] for m in metas))
        devices = ", ".join(dict.fromkeys(m.get("device", "cpu") for m in metas))
        header = f"Tables made {when} on {machines}, device {devices}"
        if any(m.get("computed_on") for m in metas):  # a run resumed on other machines
            header += " (pieces computed on several machines: see the sections)"
        if rendered:
            header += f" (rendered {time.strftime('%Y-%m-%d')} from their JSON files)"
    else:
        threads = f"torch {torch.__version__}, {torch.get_num_threads()} threads"
        header = f"{time.strftime('%Y-%m-%d')}, {machine()}, {threads}"
    parts = [f"# DiffStack: results\n\n{header}\n"]
    if tables:
        parts += [f"## The paper's claims, here\n\n{claims_card(tables)}\n"]
    for title, md, files in sections:
        parts += [f"## {title}\n\n{md}\n"] + [f"![{f}]({f})\n" for f in files]
    write_atomic(out / "report.md", "\n".join(parts))
    return out / "report.md"


def section_markdown(spec: TableSpec, meta: dict, table: str) -> str:
    """A table's provenance line, the table and the paper's numbers: its .md and report text."""
    where = [meta["date"], meta["machine"]]
    where += [f"device {meta['device']}"] if "device" in meta else []
    where += [f"{meta['seconds']:.0f} s"]
    if "piece_seconds" in meta:  # a resumed run's own seconds are only what was left
        where[-1] += (
            f" wall in this command, {meta['piece_seconds']:.0f} s of computing summed over its "
            f"{meta['pieces']} pieces ({meta['piece_cpu_seconds']:.0f} CPU s)"
        )
    where += [f"commit {meta['git_commit']}"] if meta.get("git_commit") else []
    note = f"; {meta['note']}" if meta.get("note") else ""
    if ran := meta.get("computed_on"):  # a resumed run's pieces from several machines
        where_ran = ", ".join(f"{m} ({k} piece{'s' * (k > 1)})" for m, k in ran.items())
        note += (
            f"; its pieces ran on {len(ran)} machines, and the same seed gives other numbers on "
            f"another kind of processor: {where_ran}"
        )
    if spec.paper:
        after = f"The paper's numbers:\n\n{paper_markdown(spec)}\n"
    else:
        after = f"{waymo.WAYMO_LICENCE}.\n" if spec.kind == "real" else ""
    return f"`{meta['command']}` ({', '.join(where)}{note})\n\n{table}\n\n{after}"


def table_file_markdown(spec: TableSpec, md: str) -> str:
    """out_dir/<name>.md: the title, section_markdown's text and the figures."""
    return f"# {spec.title}\n\n{md}" + "".join(f"\n![{f}]({f})\n" for f in spec.figures)
