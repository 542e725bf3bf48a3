"""What a person reads and looks at: Markdown and plots of a discovery and of a diagnosis.

- :func:`equations_markdown`: ``equations.md``, the discovered equations with their parameters
  (:func:`equation_sections`: as an engineer writes them, in LaTeX, and as Python).
- :func:`plot_scores`: the paper's Fig. 3, the best score per round of each loop.
- :func:`write_report` (with :func:`report_markdown`): the discrepancy report of
  :func:`jaxdmd.diagnose.diagnose`: ``report.md``, ``trajectories.png``, ``evidence.png``,
  ``diagnosis.json`` and, when the model was extended, ``extended_model.py``.

matplotlib is imported only when a plot is drawn.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # annotations only: report is imported by pipeline, not the reverse
    from jaxdmd.diagnose import Diagnosis
    from jaxdmd.pipeline import Discovery
    from jaxdmd.search import Equations, RoundReport, SearchState


def equations_markdown(discovery: Discovery) -> str:
    """``equations.md``: the state equations, then the algebraic ones (as an engineer writes
    them, in LaTeX, and as Python: :func:`equation_sections`)."""
    lines = ["# Discovered model", ""]
    lines += equation_sections(discovery.de, discovery.ae)
    lines += holding_section(discovery.report.get("ae", {}).get("holds"))
    lines += identities_section(discovery.report.get("ae", {}).get("identities"))
    frequency = discovery.report.get("de", {}).get("inclusion_frequency")
    searches = len(discovery.report.get("de", {}).get("searches", [])) or 1
    if frequency and searches > 1:
        lines += ["", f"## How often each term was chosen ({searches} independent searches)", ""]
        lines += ["| equation | term | share of the searches |", "|---|---|---|"]
        for target, terms in frequency.items():
            lines += [f"| d{target}/dt | `{t}` | {share:.2f} |" for t, share in terms.items()]
    lines += modes_section(discovery.report.get("modes") or [])
    test = discovery.report.get("test")
    if test:
        n = next(iter(test.values()))["n_recordings"]
        lines += ["", f"## Held-out rollouts ({n} recording(s), means over them)", ""]
        lines += rollout_table(test).splitlines()
    return "\n".join(lines) + "\n"


def holding_section(holds: Mapping[str, Any] | None) -> list[str]:
    """Markdown lines: how well each algebraic equation holds with the states unknown
    (``summary["ae"]["holds"]``, from :func:`jaxdmd.refine.refit_joint`)."""
    if not holds:
        return []
    from jaxdmd import pretty

    bar = float(holds["bar"])
    lines = ["", "## How well the algebraic equations hold", ""]
    lines += [
        "Each algebraic equation fitted with the states unknown (maximum likelihood over the "
        "noisy states, their dynamics and the clean algebraic channels): the standard deviation "
        "of its error as a share of its variable's. An equation with the right terms follows "
        f"its channel almost exactly (down to 1e-5, the fit's floor); one above {bar:g} does not: "
        "a term is missing or a stand-in takes its place, and its terms are suspect.",
        "",
        "| variable | error / deviation | holds |",
        "|---|---|---|",
    ]
    for name, share in holds["error_share"].items():
        verdict = "**no**" if name in holds["not_holding"] else "yes"
        lines.append(f"| {pretty.symbol(name)} | {share:.2g} | {verdict} |")
    return lines


def identities_section(identities: Mapping[str, Any] | None) -> list[str]:
    """Markdown lines: the relations among the measured algebraic variables
    (``summary["ae"]["identities"]``, from :func:`jaxdmd.identities.measured_identities`)."""
    from jaxdmd.identities import nmse_text

    if not identities:
        return []
    lines = ["", "## Relations among the measured algebraic variables", ""]
    lines += [
        "On the measurements, each variable below is a sum of products of the other algebraic "
        "variables (the simplest such sum within 25 % of the best held-out fit), and that "
        "relation fits it on held-out recordings at least ten times better than its line in "
        "the states. Where, written in the model's own lines of those variables (nothing "
        "measured), it also fits its variable better than that line does, and the closed "
        "model then simulates the training recordings no worse, the relation is written into "
        "the model in place of that line: the equations above then show it.",
        "",
        "| relation | held-out NMSE | the line's | in the model |",
        "|---|---|---|---|",
    ]
    for item in identities.values():
        errors = (nmse_text(item["held_out_nmse"]), nmse_text(item["line_nmse"]))
        used = "yes" if item.get("in_model") else "no"
        lines.append(f"| {item['text']} | {errors[0]} | {errors[1]} | {used} |")
    return lines


def modes_section(modes: Sequence[dict[str, Any]]) -> list[str]:
    """Markdown lines: the model's small-signal modes at each training recording's operating
    point (:func:`jaxdmd.rollout.modes`), the least damped first."""
    if not modes:
        return []
    lines = ["", "## Small-signal modes at the recorded operating points", ""]
    lines += [
        "The model linearised at each training recording's first sample (the algebraic "
        "equations closed, inputs and terminal voltage held): its largest real part and its "
        "oscillatory modes. With the terminal voltage held the machine sees an infinitely "
        "stiff bus: one that is stable in its network can be unstable here.",
        "",
        "| recording | largest real part [1/s] | stable | oscillatory: f [Hz] (damping ratio) |",
        "|---|---|---|---|",
    ]
    for m in modes:
        if "error" in m:
            lines.append(f"| {m['recording']} | - | - | {m['error']} |")
            continue
        osc = sorted(m["oscillatory"], key=lambda o: o["damping_ratio"])
        text = ", ".join(f"{o['frequency_hz']:.3g} ({o['damping_ratio']:.3g})" for o in osc)
        stable = "yes" if m["max_real"] < 0 else "**no**"
        lines.append(f"| {m['recording']} | {m['max_real']:.4g} | {stable} | {text or '-'} |")
    return lines


def equation_sections(*equations: Equations | None) -> list[str]:
    """Markdown sections of fitted equations (state equations for a DE loop's, algebraic ones
    for an AE loop's): as an engineer writes them (:mod:`jaxdmd.pretty`: e'_q, ω, signs folded),
    in LaTeX, and as Python (the lines of ``model.py`` with the fitted values written in)."""
    from jaxdmd import pretty

    found = [eq for eq in equations if eq is not None]
    lines: list[str] = []
    latex: list[str] = []
    for eq in found:
        de = eq.contract.loop == "DE"
        title = "State equations (DE loop)" if de else "Algebraic equations (AE loop)"
        lines += [f"## {title}", ""]
        for target, rhs in zip(
            eq.contract.targets, eq.readable(by_name=True).values(), strict=True
        ):
            lines.append(f"    {pretty.equation(target, rhs, dt=de)}")
            latex.append(pretty.equation(target, rhs, "latex", dt=de).replace(" = ", " &= ", 1))
        lines.append("")
    if latex:
        lines += ["## In LaTeX", "", "$$", "\\begin{aligned}"]
        lines += [f"{row} \\\\" for row in latex[:-1]] + [latex[-1], "\\end{aligned}", "$$", ""]
        lines += ["## As Python (the lines of `model.py`, fitted values written in)", ""]
        for eq in found:
            lines += [f"    {k} = {v}" for k, v in eq.readable(by_name=True).items()]
        lines.append("")
    return lines[:-1] if lines else lines


def plot_scores(path: Path, loops: Sequence[tuple[str, SearchState]]) -> None:
    """The paper's Fig. 3: best score per round of each loop, extensions marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(loops), figsize=(5.5 * len(loops), 3.6), squeeze=False)
    for ax, (name, state) in zip(axes[0], loops, strict=True):
        history = np.asarray(state.history)
        ax.plot(np.arange(len(history)), -history, marker="o", lw=1.5)
        ax.set_yscale("log")
        ax.set_xlabel("round")
        ax.set_ylabel("-s* (mean NMSE)")
        ax.set_title(f"{name} loop")
        ax.axhline(state.config.gamma, color="grey", ls=":", lw=1, label="gamma")
        joined: dict[int, list[str]] = {}
        for var, rnd in state.joined:
            if rnd > 0:
                joined.setdefault(rnd, []).append(var)
        for rnd, names in joined.items():
            ax.axvline(rnd, color="green", ls="--", lw=0.8)
            ax.text(
                rnd + 0.15,
                0.97,
                "+ " + ", ".join(names),
                transform=ax.get_xaxis_transform(),
                rotation=90,
                va="top",
                ha="left",
                fontsize=8,
                color="green",
            )
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


class Progress:
    """One line per round on the terminal (rich): a :class:`jaxdmd.pipeline.Observer`.

    :meth:`log_to` copies every line printed through :meth:`print` or :meth:`message` (those
    before the call included) as plain text into a file, e.g. the run folder's ``run.log``.
    """

    def __init__(self, quiet: bool = False):
        import time

        from rich.console import Console

        self.console = Console(stderr=True, quiet=quiet, highlight=False)
        self._clock = time.perf_counter
        self.start = self._clock()
        self._pending: list[tuple[str, bool]] = []  # printed before log_to: (text, markup)
        self._log = None  # the log file's Console, once log_to is called
        self._log_file = None

    def print(self, text: str, markup: bool = True) -> None:
        """Show ``text`` and copy it to the log: rich markup, wrapped to the terminal, or with
        ``markup=False`` as it is (equations, tables: no markup, long lines not wrapped)."""
        self.console.print(text, markup=markup, soft_wrap=not markup)
        if self._log is None:
            self._pending.append((text, markup))
        else:
            self._log.print(text, markup=markup, soft_wrap=not markup)
            self._log_file.flush()

    def log_to(self, path: str | Path) -> None:
        """Append the lines shown so far, and from now on every line, to ``path`` (plain text)."""
        import datetime

        from rich.console import Console

        self.close()
        self._log_file = open(path, "a", encoding="utf-8")  # noqa: SIM115 (closed by close())
        self._log = Console(
            file=self._log_file, width=160, no_color=True, highlight=False, emoji=False
        )
        now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
        self._log.print(f"# jaxdmd, started {now}", markup=False)
        for text, markup in self._pending:
            self._log.print(text, markup=markup, soft_wrap=not markup)
        self._pending.clear()
        self._log_file.flush()

    def close(self) -> None:
        """Close the log file (if any); later lines are shown only."""
        if self._log_file is not None:
            self._log_file.close()
        self._log = self._log_file = None

    def message(self, text: str) -> None:
        self.print(text)

    def loop_started(self, name: str, state: SearchState) -> None:
        lib = ", ".join(state.contract.arguments)
        self.print(
            f"[bold]{name} loop[/bold]: targets {', '.join(state.contract.targets)}; "
            f"arguments {lib}; seed score {state.history[0]:.4g}"
        )

    def round(self, name: str, state: SearchState, report: RoundReport) -> None:
        dropped = sum(n for _, n in report.dropped)
        # valid and dropped count the same candidates: the samples and the recombined one
        total = report.n_samples + report.n_recombined
        line = (
            f"  {name} round {report.round:2d}  best {report.best_score:10.4g}  "
            f"valid {report.n_valid:2d}/{total:2d} (dropped {dropped})  "
            f"{self._clock() - self.start:6.1f}s"
        )
        if report.joined:
            line += f"  [green]+ {', '.join(report.joined)}[/green]"
        if report.missing:
            line += f"  [yellow]not measured: {', '.join(report.missing)}[/yellow]"
        if report.done:
            line += f"  [bold]done: {report.stop_reason}[/bold]"
        self.print(line)


def rollout_summary(scores: Sequence[dict]) -> dict:
    """The mean over recordings of :func:`jaxdmd.rollout.score` results: per state and over
    states (MAPE, R^2, NRMSE), how many rollouts diverged, and how many are far off (diverged,
    or a state's R^2 below ``FAR_OFF_R2`` = -10: ``n_far_off``, and per state the number of
    recordings where it is far off, ``far_off_states``)."""
    from jaxdmd.rollout import METRICS

    if not scores:
        return {}
    states = list(scores[0]["full"]["per_state"])

    def mean(values: Sequence[float]) -> float:
        return float(np.mean(values))

    return {
        "mean": {k: mean([s["full"]["mean"][k] for s in scores]) for k in METRICS},
        "per_state": {
            st: {k: mean([s["full"]["per_state"][st][k] for s in scores]) for k in METRICS}
            for st in states
        },
        "n_recordings": len(scores),
        "n_diverged": sum(1 for s in scores if s.get("diverged")),
        "n_far_off": sum(1 for s in scores if s.get("far_off")),
        "far_off_states": {
            st: n
            for st in states
            if (n := sum(1 for s in scores if st in s.get("far_off_states", ())))
        },
    }


def rollout_table(test: dict) -> str:
    """Held-out rollout metrics as a small Markdown table (one row per mode and state)."""
    lines = ["| rollout | state | MAPE [%] | R^2 | NRMSE |", "|---|---|---|---|---|"]
    for mode, label in (("de", "DE (algebraic played in)"), ("dae", "DAE (closed)")):
        if mode not in test:
            continue
        row = test[mode]
        for st, m in [*row["per_state"].items(), ("mean", row["mean"])]:
            lines.append(f"| {label} | {st} | {m['mape']:.4g} | {m['r2']:.5g} | {m['nrmse']:.3g} |")
        if row["n_diverged"]:
            lines.append(f"| {label} | diverged | {row['n_diverged']}/{row['n_recordings']} | | |")
        if row.get("n_far_off"):
            far = ", ".join(f"{st} ({n})" for st, n in row.get("far_off_states", {}).items())
            lines.append(
                f"| {label} | far off (diverged or R^2 < -10) | "
                f"{row['n_far_off']}/{row['n_recordings']} | {far} | |"
            )
    return "\n".join(lines) + "\n"


def plot_trajectories(path: Path, recording, simulations: dict) -> None:
    """Measured against simulated states of one held-out recording (``trajectories.png``):
    ``simulations`` maps a label (e.g. "DE", "DAE") to a :class:`jaxdmd.rollout.RolloutResult`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(simulations.values()))
    states = list(first.states)
    t = np.asarray(recording.t)
    fig, axes = plt.subplots(len(states), 1, figsize=(9, 1.9 * len(states) + 0.6), sharex=True)
    axes = np.atleast_1d(axes)
    styles = {"DE": ("tab:orange", "--"), "DAE": ("tab:blue", "-")}
    for ax, s in zip(axes, states, strict=True):
        meas = np.asarray(recording[s])
        ax.plot(t, meas, color="black", lw=2.2, alpha=0.35, label="measured")
        for label, sim in simulations.items():
            color, ls = styles.get(label, (None, "-"))
            ax.plot(t, sim[s], color=color, ls=ls, lw=1.1, label=f"simulated ({label})")
        pad = 0.5 * float(np.ptp(meas)) + 1e-9
        ax.set_ylim(float(meas.min()) - pad, float(meas.max()) + pad)
        ax.set_ylabel(s)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, ncol=3)
    axes[0].set_title(f"{recording.label or 'held-out recording'}: measured and simulated")
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------
# the discrepancy report (jaxdmd.diagnose)
# ------------------------------------------------------------------------------------------------


def _plot_diagnosis_trajectories(path: Path, d: Diagnosis) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxdmd.rollout import fault_window

    states = d.model.targets
    ds = d.test[0]
    t = np.asarray(ds.t)
    fig, axes = plt.subplots(2, len(states), figsize=(3.6 * len(states), 5.2), squeeze=False)
    window = fault_window(ds)
    labels = {
        "given": "model (given parameters)",
        "refit": "model (refitted parameters)",
        "extended": "extended",
    }
    colors = {"given": "tab:red", "refit": "tab:orange", "extended": "tab:green"}
    for i, s in enumerate(states):
        top, bottom = axes[0, i], axes[1, i]
        top.plot(t, ds[s], color="black", lw=1.2, label="measured")
        for name, sims in d.rollouts.items():
            top.plot(t, sims[0][s], color=colors[name], lw=0.9, ls="--", label=labels[name])
            bottom.plot(t, sims[0][s] - np.asarray(ds[s]), color=colors[name], lw=0.9)
        for ax in (top, bottom):
            if window is not None:
                ax.axvspan(*window, color="0.9", zorder=0)
        top.set_title(s)
        bottom.set_xlabel("t [s]")
        bottom.axhline(0, color="0.5", lw=0.5)
    axes[0, 0].legend(fontsize=7)
    axes[1, 0].set_ylabel("simulated - measured")
    fig.suptitle(f"held-out: {ds.label or 'recording 1'} (grey: fault window)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_evidence(path: Path, d: Diagnosis) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eqs = list(d.candidates)
    fig, axes = plt.subplots(1, len(eqs), figsize=(3.4 * len(eqs), 3.4), squeeze=False)
    for ax, eq in zip(axes[0], eqs, strict=True):
        cands = d.candidates[eq][:6][::-1]
        colors = ["tab:red" if c.new_variables else "tab:blue" for c in cands]
        ax.barh([c.term[:28] for c in cands], [max(c.explained, 0) for c in cands], color=colors)
        ax.set_xlim(0, 1)
        ax.set_title(f"d{eq}/dt", fontsize=9)
        ax.axvline(0.2, color="0.5", lw=0.6, ls=":")
        ax.tick_params(labelsize=7)
    axes[0, 0].set_xlabel("share of held-out residual explained\n(red: a variable the model lacks)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt(x: float | None) -> str:
    if x is None:
        return "-"
    return f"{x:.3g}" if np.isfinite(x) else str(x)


_COLUMNS = {"given": "given parameters", "refit": "refitted parameters", "extended": "extended"}
"""The report's name for each result of a diagnosis (the keys of its ``nmse``, ``metrics``)."""


def _columns(results: dict[str, object]) -> list[str]:
    """The keys of ``results`` in the report's order: given, refitted, extended."""
    return [k for k in _COLUMNS if k in results]


def physical_table(reports: dict) -> list[str]:
    """The ``## Physical parameters`` section of a diagnosis: one column per model (given,
    refitted, extended), each parameter :func:`jaxdmd.physical.physical_parameters` maps, as
    ``value ± standard error`` where one is known (`PhysicalParameter.text`); empty when no
    model maps to a machine-model family."""
    cols = [k for k in _COLUMNS if k in reports]
    if not any(reports[k].family for k in cols):
        return []
    with_errors = [_COLUMNS[k] for k in cols if any(p.stderr for p in reports[k].parameters)]
    if with_errors:
        errors = (
            f"{', '.join(with_errors)}: ± one standard error of the fit to the training data "
            "(`docs/diagnose.md`)"
            + ("; given parameters: none, they were not fitted" if "given" in cols else "")
        )
    else:
        errors = "no standard errors here"
    out = ["## Physical parameters", ""]
    out.append(
        "Family: "
        + ", ".join(f"{_COLUMNS[k]} **{reports[k].family or 'none'}**" for k in cols)
        + f" (`jaxdmd.physical`; on the data's per-unit base; {errors})."
    )
    names: list[str] = []
    for k in cols:
        names += [p.name for p in reports[k].parameters if p.name not in names]
    out += ["", "| parameter | unit | " + " | ".join(_COLUMNS[k] for k in cols) + " | note |"]
    out.append("|---|---|" + "---|" * len(cols) + "---|")
    for n in names:
        found = [reports[k].get(n) for k in cols]
        unit = next(p.unit for p in found if p is not None)
        cells = []
        for p in found:
            if p is None:
                cells.append("-")
            elif p.note == "not in the model":
                cells.append("0 (not in the model)")
            else:
                cells.append(p.text())
        note = next((p.note for p in found if p is not None and p.note != "not in the model"), "")
        out.append(f"| {n} | {unit} | " + " | ".join(cells) + f" | {note} |")
    for k in cols:
        bad = [e for e in reports[k].equations if not e.matched]
        if bad:
            terms = "; ".join(
                f"{e.equation}: {', '.join(f'`{t}`' for t in e.unmatched) or 'missing terms'}"
                for e in bad
            )
            out.append(f"\n{_COLUMNS[k]}: terms no family has: {terms}.")
    out.append("")
    return out


def report_markdown(d: Diagnosis) -> str:
    """``report.md``: the cause, the evidence, the errors, the extension and the gain.

    Every table and model says whether it used the parameters the model came with (``given``)
    or parameters refitted on the training data; a model without parameters is only refitted.
    The models are printed as an engineer writes them (:mod:`jaxdmd.pretty`), followed by their
    physical parameters side by side (:func:`physical_table`) when one maps to a family.
    """
    from jaxdmd import pretty
    from jaxdmd.diagnose import input_caveat

    states = d.model.targets
    out = [f"# Diagnosis of `{d.model.name}`", ""]
    out += [
        "Parameters: "
        + (
            "given with the model, and refitted on the training data for comparison."
            if d.given is not None
            else "no parameters given with the model; they are refitted on the training data."
        ),
        "",
    ]
    if d.assumptions:
        out += ["## Not measured", ""]
        out += [f"- {a}." for a in d.assumptions]
        out += [
            "",
            "A term found in an equation such an input enters may stand in for the input's "
            "variation.",
            "",
        ]
    out += [f"**Cause ({d.cause.kind})**: {d.cause.summary}.", ""]
    for c in d.also:
        caveat = input_caveat(c.equation, d.unmeasured)
        out.append(
            f"Also: d{c.equation}/dt, {c.term} explains {c.explained:.0%} of its residual"
            + (f" (caveat: {caveat})." if caveat else ".")
        )
    out += ["", f"Held-out data: {d.held_out}.", ""]
    out += ["## What the simulation gets wrong", "", "![trajectories](trajectories.png)", ""]
    errors_of = "its given parameters" if d.errors_of == "given" else "refitted parameters"
    out += [
        f"RMS error over the range of each state, the model with {errors_of} on the first "
        "held-out recording:",
        "",
        "| state | whole | before fault | fault window | after fault | worst | drifts |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in states:
        e = d.errors[s]
        out.append(
            f"| {s} | {_fmt(e['whole'])} | {_fmt(e.get('before fault'))} | "
            f"{_fmt(e.get('fault window'))} | {_fmt(e.get('after fault'))} | {e['worst']} | "
            f"{'yes' if e['drift'] else 'no'} |"
        )
    out += ["", "## Evidence", "", "![evidence](evidence.png)", ""]
    fits = _columns(d.nmse)
    out += [
        "Fit of each state equation on the training data (NMSE of "
        + (
            f"the increments over {d.window:g} s windows, the integral form):"
            if d.window
            else "the derivatives):"
        ),
        "",
        "| equation | " + " | ".join(_COLUMNS[k] for k in fits) + " |",
        "|---|" + "---|" * len(fits),
    ]
    for s in states:
        out.append(f"| d{s}/dt | " + " | ".join(_fmt(d.nmse[k].get(s)) for k in fits) + " |")
    out += [
        "",
        "Best single terms per equation (share of the residual they remove on held-out folds):",
        "",
    ]
    for eq, cands in d.candidates.items():
        shown = ", ".join(f"{c.term} {c.explained:.0%}" for c in cands[:4])
        out.append(f"- d{eq}/dt: {shown}")
    out += ["", "## Held-out error before and after", ""]
    cols = _columns(d.metrics)
    out += [
        "| metric | " + " | ".join(_COLUMNS[c] for c in cols) + " |",
        "|---|" + "---|" * len(cols),
    ]
    for k in ("nrmse", "mape", "r2"):
        out.append(f"| {k} | " + " | ".join(_fmt(d.metrics[c][k]) for c in cols) + " |")
    before = _COLUMNS["given" if "given" in d.metrics else "refit"]
    after = _COLUMNS["extended" if "extended" in d.metrics else "refit"]
    out.append("")
    if before != after:
        out += [f"Error ratio before ({before}) / after ({after}): **{d.gain:.1f}x**.", ""]
    out += ["## Models", ""]
    for name, eq in (("given", d.given), ("refit", d.refit), ("extended", d.extended)):
        if eq is None:
            continue
        out += [f"{_COLUMNS[name]}:", "", "```"]
        out += [
            pretty.equation(t, rhs)
            for t, rhs in zip(eq.contract.targets, eq.readable(by_name=True).values(), strict=True)
        ]
        out += ["```", ""]
    if d.extended is not None:
        out += [
            "(As Python: the extended model in `extended_model.py`, every model in "
            "`diagnosis.json`.)",
            "",
        ]
    out += physical_table(d.physical())
    if d.extended is not None:
        out.append(
            f"Extension: {d.extension_rounds} rounds of the search seeded with the model"
            + (f"; joined: {', '.join(d.joined)}" if d.joined else "")
            + "."
        )
    out.append(f"\nWall time {d.wall_time_s:.1f} s.")
    return "\n".join(out) + "\n"


def write_report(out: str | Path, d: Diagnosis) -> Path:
    """Write ``report.md``, ``trajectories.png``, ``evidence.png``, ``diagnosis.json`` and, when
    the model was extended, ``extended_model.py``; returns the report's path."""
    from jaxdmd import search

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    _plot_diagnosis_trajectories(out / "trajectories.png", d)
    _plot_evidence(out / "evidence.png", d)
    search.write_json_atomic(out / "diagnosis.json", d.to_dict())
    if d.extended is not None:
        e = d.extended
        (out / "extended_model.py").write_text(
            '"""Model extended by jaxdmd diagnose."""\n\nimport jax.numpy as jnp  # noqa: F401\n\n'
            f"{e.source.rstrip()}\n\nPARAMS = {list(e.params)!r}\n"
            f"TARGETS = {list(e.contract.targets)!r}\n"
        )
    path = out / "report.md"
    path.write_text(report_markdown(d))
    return path
