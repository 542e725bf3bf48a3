"""A discovered model written for other simulators (issue #18, item 3).

:func:`standard_machine` reads the machine-model family and the physical parameters of a
:class:`jaxdmd.pipeline.Discovery` (:func:`jaxdmd.physical.physical_parameters`) and names the
standard model they map to:

- ``classical`` -> **GENCLS** (H, D; in ANDES also x'_d, r_a, f_n): exact;
- ``one-axis`` -> **GENSAL** (PSS/E only; ANDES has no GENSAL);
- ``psat-5.1`` -> **GENROU**, exact with saturation off: x''_d = x''_q = x'_d (PSAT 5.1's
  stator puts x'_d on both axes; in ANDES's GENROU the d-axis damper then decouples, so the d
  axis is PSAT's one-state axis and T''_d0 has no effect), and GENROU's T'_q0, T''_q0, x'_q
  solved so that its q-axis operational reactance equals PSAT's (:func:`genrou_q_axis`; on the
  39-bus data they differ from PSAT's by up to about 10 %: not the same quantities). The
  PSS/E record carries the same numbers (ANDES's GENROU follows PSS/E's, via OpenIPSL; not
  checked in PSS/E itself).
  GENROU's and PSAT's states are then one linear system in other coordinates (e'_q and e''_d
  are GENROU's e'_q and psi''_q, PSAT's e'_d a combination of GENROU's e'_d and psi_kq). Where
  no such q axis exists (x'_q < x'_d, e.g. bus 30 of the 39-bus data, with x_l = 0; a
  negative ``x_l`` given with ``assume=`` finds one) or x''_d is given, the q axis is written
  as identified and the record says it approximates;
- ``two-axis`` -> **GENROU** as PSAT 5.1 with an assumed fast T''_q0 (the two-axis model is
  PSAT 5.1's limit T''_q0 -> 0, gamma_q -> 0): close, exact only in that limit.

What a discovered model does not identify is assumed and listed in the record's comment
(:data:`ASSUMED`, ``assume=`` overrides): T''_d0, leakage x_l (only GENROU's q-axis numbers
depend on it), saturation (off), and for ``one-axis`` also T''_q0 and x''_d.

A model outside these families (an equation with a term no family has, a state no family has)
is refused with :class:`ExportError`; its exact form is the Python module
(:meth:`jaxdmd.pipeline.Discovery.module_source`, ``model.py``), which
``jaxdmd.load(path).simulate(recording)`` rolls out (:func:`write_module`).

Formats (:func:`export`, the ``jaxdmd export RUN_DIR --format dyr,andes,py`` command):

- ``dyr``: a PSS/E dynamic-data record (:func:`dyr_record`). H and D are on the base the data
  are in per unit (the benchmark's 100 MVA system base): set MBASE to it in the ``.raw`` file
  or rescale them by MBASE / base. The record ends with ``/`` followed by a comment (what PSS/E
  and ANDES ignore) that states the family and the assumptions.
- ``andes``: an ANDES case (its JSON format, ``andes.load(path)``; :func:`andes_case`): a single
  machine behind a line to an infinite bus (Slack, 1 pu, 0 rad), a PV generator setting the
  operating point, the machine (GENCLS or GENROU, constant field voltage and mechanical power),
  and a bolted-type fault at the machine bus. E'_q (and the other initial states) come from
  ANDES's power flow at that operating point: the discovered model's constant terms (E'/x'_d of
  a classical stator line, P_m/M) are not written; they hold for the operating point the data
  were recorded at. Writing it does not need ANDES (``pip install jaxdmd[export]`` to run it).
- ``py``: the model as jaxdmd's Python module (``model.py``), for any structure.

Given the training recordings (``export(..., fitted_to=train)``, ``jaxdmd export --data``),
the records hold the standard machine fitted as a whole (:func:`fit_standard`): PSAT 5.1 with
its parameters tied as the family ties them (:func:`tied_source`), fitted by least squares on
the model-smoothed recordings and then by how it simulates them; a discovered model with
PSAT 5.1's states and stand-in terms is projected on the family that way. The tied model is
written as ``standard_model.py``: its rollout is what the records simulate.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jaxdmd.physical import PhysicalReport, physical_parameters

__all__ = [
    "ASSUMED",
    "FORMATS",
    "ExportError",
    "StandardFit",
    "StandardMachine",
    "andes_case",
    "dyr_record",
    "export",
    "fit_standard",
    "genrou_q_axis",
    "standard_machine",
    "tied_source",
    "write_module",
]

FORMATS = ("dyr", "andes", "py")

NOMINAL_HZ = (50.0, 60.0)
"""The power systems' frequencies: a discovered Omega_b within 2 % of one is taken as it in the
tied standard model (:func:`tied_source`), not fitted (the rotor angle's simulation cannot
tell Omega_b from 1/M well: they trade along Omega_b / M)."""

ASSUMED: dict[str, float] = {
    "T''_d0": 0.03,  # s, GENROU/GENSAL's d-axis damper (no effect on GENROU when x''_d = x'_d)
    "T''_q0": 0.05,  # s, GENSAL's q axis (one-axis), the fast q axis of a two-axis model
    "xpp_ratio": 0.8,  # GENSAL (one-axis): x''_d = x''_q = xpp_ratio x'_d
    "x_l": 0.0,  # pu, leakage reactance (not identified)
    "S(1.0)": 0.0,  # saturation (not identified)
    "S(1.2)": 0.0,
}
"""Values a discovered model does not identify and GENSAL/GENROU need (``assume=`` replaces
any of them; ``x''_d`` may be given instead of ``xpp_ratio``, and for GENROU instead of
x''_d = x'_d, which makes the record approximate)."""


class ExportError(ValueError):
    """The model cannot be written in the asked format (the message says why and what to do)."""


@dataclass(frozen=True)
class StandardMachine:
    """The standard model a discovered machine maps to.

    Attributes:
        family: the physical family (:mod:`jaxdmd.physical`).
        model: ``GENCLS``, ``GENSAL`` or ``GENROU``.
        params: the parameters by their physical names (``H``, ``D``, ``x'_d``, ``T'_d0``...),
            identified ones and assumed ones.
        assumed: the names of ``params`` that were assumed, not identified.
        notes: what differs from the discovered model.
    """

    family: str
    model: str
    params: dict[str, float]
    assumed: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    report: PhysicalReport | None = field(default=None, repr=False, compare=False)

    def comment(self) -> str:
        """One line: where the record comes from and what it assumes."""
        parts = [f"jaxdmd: discovered {self.family} model -> {self.model}"]
        if self.assumed:
            parts.append(
                "assumed (not identified): "
                + ", ".join(f"{k} = {self.params[k]:.6g}" for k in self.assumed)
            )
        parts += list(self.notes)
        return "; ".join(parts)


def _value(report: PhysicalReport, name: str) -> float | None:
    p = report.get(name)
    if p is None or not math.isfinite(p.value):
        return None
    return float(p.value)


def standard_machine(discovery: Any, assume: Mapping[str, float] | None = None) -> StandardMachine:
    """The standard model ``discovery`` maps to, or :class:`ExportError` saying why none.

    ``discovery``: a :class:`jaxdmd.pipeline.Discovery` (its ``de``, ``ae``) or a
    :class:`jaxdmd.physical.PhysicalReport`. ``assume``: values for what the discovery does not
    identify (:data:`ASSUMED`), and for an identified parameter, a replacement.
    """
    if isinstance(discovery, PhysicalReport):
        report = discovery
    else:
        report = physical_parameters(discovery.de, getattr(discovery, "ae", None))
    assume = dict(assume or {})
    if report.family is None:
        raise ExportError(
            "the discovered equations match no standard machine model ("
            + "; ".join(report.notes or ("no family",))
            + "): export the Python module instead (format 'py')"
        )
    outside = [n for n in report.notes if n.startswith(f"{report.family}: the largest family")]
    bad = [e for e in report.equations if not e.matched]
    if outside or bad:
        what = "; ".join(
            [
                *outside,
                *(f"{e.equation} has {', '.join(e.unmatched) or 'missing terms'}" for e in bad),
            ]
        )
        raise ExportError(
            f"the model is not a standard {report.family} machine ({what}): no standard record "
            "holds it; export the Python module instead (format 'py')"
        )
    family = report.family
    values: dict[str, float] = {}
    assumed: list[str] = []
    notes: list[str] = [
        f"{p.source}: constant {p.value:.3g} ± {p.stderr:.2g} set aside (not written; {p.note})"
        for p in report.parameters
        if p.name == "constant term (set aside)" and p.stderr is not None
    ]

    def need(name: str, *alternatives: str) -> float:
        if name in assume:
            values[name] = float(assume[name])
            return values[name]
        for n in (name, *alternatives):
            v = _value(report, n)
            if v is not None:
                values[name] = v
                return v
        raise ExportError(
            f"the discovered {family} model does not identify {name} (needed by the standard "
            f"record): give it with assume={{{name!r}: value}}, or export format 'py'"
        )

    def optional(name: str, default: float, note: str = "") -> float:
        if name in assume:
            values[name] = float(assume[name])
        else:
            v = _value(report, name)
            values[name] = default if v is None else v
            if v is None and note:
                notes.append(note)
        return values[name]

    def assumed_value(name: str) -> float:
        values[name] = float(assume.get(name, ASSUMED[name]))
        assumed.append(name)
        return values[name]

    need("H")
    values["M"] = 2 * values["H"]
    d = report.get("D")
    values["D"] = float(assume.get("D", d.value if d is not None else 0.0))
    if d is not None and d.note == "not in the model":
        notes.append("D = 0: the swing equation has no damping term")
    omega_b = optional("Omega_b", 2 * math.pi * 60, "Omega_b not identified: 60 Hz assumed")
    values["f_n"] = omega_b / (2 * math.pi)
    optional("r_a", 0.0, "r_a not identified: 0 assumed")
    if family == "classical":
        try:
            need("x'_d")
        except ExportError:
            notes.append("x'_d not identified (no stator lines): GENCLS needs it in ANDES only")
        return StandardMachine(family, "GENCLS", values, tuple(assumed), tuple(notes), report)

    xdp = need("x'_d")
    need("T'_d0")
    values["x_d"] = xdp + need("x_d - x'_d")
    if family == "one-axis":
        need("x_q")
        assumed_value("T''_d0")
        assumed_value("T''_q0")
        if "x''_d" in assume:
            values["x''_d"] = float(assume["x''_d"])
        else:
            values["x''_d"] = assumed_value("xpp_ratio") * xdp
        assumed.append("x''_d")
        for name in ("x_l", "S(1.0)", "S(1.2)"):
            assumed_value(name)
        return StandardMachine(family, "GENSAL", values, tuple(assumed), tuple(notes), report)

    # two-axis, psat-5.1 -> GENROU with x''_d = x''_q = x'_d and the q axis solved
    need("T'_q0")
    if family == "two-axis":
        values["x_q"] = need("x'_q") + need("x_q - x'_q")
        assumed_value("T''_q0")
        notes.append(
            "two-axis written as PSAT 5.1 with a fast T''_q0 (the two-axis model is its limit "
            "T''_q0 -> 0): exact only in that limit"
        )
    else:  # psat-5.1
        need("x_q")
        need("x'_q")
        need("T''_q0")
    assumed_value("T''_d0")
    exact_d = "x''_d" not in assume
    if exact_d:
        values["x''_d"] = xdp
        notes.append(
            "x''_d = x''_q = x'_d (PSAT 5.1's stator; GENROU's d-axis damper then decouples, "
            "so its d axis is PSAT's and T''_d0 has no effect)"
        )
    else:
        values["x''_d"] = float(assume["x''_d"])
        assumed.append("x''_d")
    for name in ("x_l", "S(1.0)", "S(1.2)"):
        assumed_value(name)
    psat_q = {k: values[k] for k in ("x'_q", "T'_q0", "T''_q0")}
    q = (
        genrou_q_axis(
            values["x_q"], psat_q["x'_q"], xdp, psat_q["T'_q0"], psat_q["T''_q0"], values["x_l"]
        )
        if exact_d
        else None
    )
    if q is not None:
        values.update({f"{k} (PSAT)": v for k, v in psat_q.items()})
        values.update(q)
        notes.append(
            "GENROU's T'_q0, T''_q0, x'_q solved so that its q-axis operational reactance equals "
            "PSAT 5.1's (PSAT's "
            + ", ".join(f"{k} = {v:.6g}" for k, v in psat_q.items())
            + "): with saturation off the record reproduces PSAT 5.1 exactly"
        )
    else:
        why = (
            "x''_d given"
            if not exact_d
            else f"no GENROU q axis with x_l = {values['x_l']:.6g} has PSAT 5.1's"
        )
        notes.append(
            f"GENROU's q axis approximates PSAT 5.1's ({why}): T'_q0, T''_q0, x'_q written as "
            "identified"
        )
    return StandardMachine(family, "GENROU", values, tuple(assumed), tuple(notes), report)


def genrou_q_axis(
    x_q: float, x_qp: float, x_dp: float, t_qp: float, t_qpp: float, x_l: float = 0.0
) -> dict[str, float] | None:
    """GENROU's ``T'_q0``, ``T''_q0``, ``x'_q`` (with ``x''_q = x'_d`` and leakage ``x_l``)
    whose q axis is PSAT 5.1's, or None when none exists.

    With the stator ``v_d + r_a i_d = e''_d + x'_d i_q`` of both models the q axis is one
    linear map, ``v_d + r_a i_d = X_q(s) i_q``. PSAT 5.1's (its ``gamma_q`` makes it the
    classical form, short-circuit time constants ``T'_q = T'_q0 x'_q / x_q``,
    ``T''_q = T''_q0 x'_d / x'_q``)::

        X_q(s) = x_q (1 + s T'_q)(1 + s T''_q) / ((1 + s T'_q0)(1 + s T''_q0))

    ANDES's GENROU (``genrou.py``: states e'_d, psi''_q; ``x''_q = x'_d``; with its
    ``T'_q0 = a``, ``T''_q0 = b``, ``x'_q = y``, ``A = x_q - y``, ``C = y - x'_d``,
    ``B = y - x_l``, ``k = A C / B^2``, ``g = (x'_d - x_l) / B``)::

        X_q(s) = [x_q + s (y a + b (x'_d (1 + k) + A g^2)) + s^2 x'_d a b]
                 / [1 + s (a + b (1 + k)) + s^2 a b]

    Equal high-frequency and static values; the rest is three equations in (a, b, y):
    ``a b = T'_q0 T''_q0``, ``a + b (1 + k) = T'_q0 + T''_q0`` and
    ``C a + A g^2 b = T'_q0 (x'_q + gamma_q - x'_d)`` (PSAT's values on the right). For a
    given y the first two give a, b (a >= b); the third is solved for y on ``(x_l, x_q)``
    (scan, then bisection; the root nearest PSAT's x'_q). None when there is no root, e.g.
    bus 30 of the IEEE 39-bus data (x'_q < x'_d: PSAT's zeros do not interlace its poles) with
    x_l = 0.
    """
    t1, t2 = float(t_qp), float(t_qpp)
    if min(t1, t2, x_qp, x_dp) <= 0 or x_q <= x_l or x_dp <= x_l:
        return None
    gamma_q = (x_dp / x_qp) * (t2 / t1) * (x_q - x_qp)
    rhs = t1 * (x_qp + gamma_q - x_dp)

    def solve(y: float) -> tuple[float, float, float] | None:
        a_, c_, b_ = x_q - y, y - x_dp, y - x_l
        k = a_ * c_ / b_**2
        disc = (t1 + t2) ** 2 - 4 * (1 + k) * t1 * t2
        if 1 + k <= 0 or disc < 0:
            return None
        b = (t1 + t2 - math.sqrt(disc)) / (2 * (1 + k))
        if b <= 0:
            return None
        a = t1 * t2 / b
        g = (x_dp - x_l) / b_
        return a, b, c_ * a + a_ * g * g * b - rhs

    n = 2000
    grid = [x_l + (x_q - x_l) * i / n for i in range(1, n)]
    roots = []
    prev: tuple[float, float] | None = None
    for y in grid:
        r = solve(y)
        if r is None:
            prev = None
            continue
        if r[2] == 0.0:
            roots.append(y)
        elif prev is not None and (prev[1] < 0) != (r[2] < 0):
            lo, hi, f_lo = prev[0], y, prev[1]
            for _ in range(200):
                mid = (lo + hi) / 2
                rm = solve(mid)
                if rm is None:
                    break
                if (rm[2] < 0) == (f_lo < 0):
                    lo, f_lo = mid, rm[2]
                else:
                    hi = mid
                if hi - lo <= 1e-15 * max(1.0, abs(hi)):
                    break
            roots.append((lo + hi) / 2)
        prev = (y, r[2])
    found = [(y, solve(y)) for y in roots]
    found = [(y, r) for y, r in found if r is not None and abs(r[2]) <= 1e-9 * max(1.0, abs(rhs))]
    if not found:
        return None
    y, (a, b, _) = min(found, key=lambda yr: abs(yr[0] - x_qp))
    return {"T'_q0": a, "T''_q0": b, "x'_q": y}


# ----------------------------------------------------------------------------------------------
# PSS/E


def _num(x: float) -> str:
    return f"{x:.6g}"


def dyr_record(
    discovery: Any,
    bus: int = 1,
    machine_id: str = "1",
    assume: Mapping[str, float] | None = None,
) -> str:
    """The PSS/E ``.dyr`` record of the standard model ``discovery`` maps to (module docstring):

    - GENCLS: ``IBUS 'GENCLS' ID H D /``;
    - GENSAL: ``IBUS 'GENSAL' ID T'do T''do T''qo H D Xd Xq X'd X''d Xl S(1.0) S(1.2) /``;
    - GENROU: ``IBUS 'GENROU' ID T'do T''do T'qo T''qo H D Xd Xq X'd X'q X''d Xl S(1.0)
      S(1.2) /``.

    A comment after the ``/`` names the family and the assumed values. Raises
    :class:`ExportError` for a model no standard record holds."""
    m = discovery if isinstance(discovery, StandardMachine) else standard_machine(discovery, assume)
    p = m.params
    if m.model == "GENCLS":
        fields = [p["H"], p["D"]]
    elif m.model == "GENSAL":
        fields = [p["T'_d0"], p["T''_d0"], p["T''_q0"], p["H"], p["D"], p["x_d"], p["x_q"]]
        fields += [p["x'_d"], p["x''_d"], p["x_l"], p["S(1.0)"], p["S(1.2)"]]
    else:
        fields = [p["T'_d0"], p["T''_d0"], p["T'_q0"], p["T''_q0"], p["H"], p["D"]]
        fields += [p["x_d"], p["x_q"], p["x'_d"], p["x'_q"], p["x''_d"], p["x_l"]]
        fields += [p["S(1.0)"], p["S(1.2)"]]
    head = f"{bus} '{m.model}' {machine_id}"
    values = [_num(v) for v in fields]
    rows = [" ".join([head, *values[:6]])]
    rows += [" ".join(values[i : i + 6]) for i in range(6, len(values), 6)]
    base = "H, D on the data's per-unit power base (set MBASE to it)"
    return "\n".join(rows) + f" / {m.comment()}; {base}\n"


# ----------------------------------------------------------------------------------------------
# ANDES


def andes_case(
    discovery: Any,
    *,
    p0: float = 0.8,
    v0: float = 1.0,
    x_line: float = 0.3,
    fault: tuple[float, float] | None = (1.0, 1.1),
    fault_x: float = 0.05,
    vn: float = 110.0,
    assume: Mapping[str, float] | None = None,
) -> dict[str, list[dict[str, Any]]]:
    """An ANDES case (its JSON format as a dict) of the machine ``discovery`` maps to, on a
    single-machine-infinite-bus system (module docstring).

    Args:
        discovery: a :class:`jaxdmd.pipeline.Discovery` or a :class:`StandardMachine`.
        p0: the machine's active power in per unit of the 100 MVA base (the PV generator).
        v0: the machine's terminal voltage magnitude (pu).
        x_line: the reactance of the line to the infinite bus (pu).
        fault: fault-on and clearing times (s) of a fault at the machine bus; None: no fault.
        fault_x: the fault reactance (pu).
        vn: the buses' rated voltage (kV; nothing depends on it).
        assume: see :func:`standard_machine`.
    """
    m = discovery if isinstance(discovery, StandardMachine) else standard_machine(discovery, assume)
    p = m.params
    common = {"idx": "GEN1", "bus": 1, "gen": "PV1", "Sn": 100.0, "Vn": vn, "fn": p["f_n"]}
    common |= {"M": p["M"], "D": p["D"], "ra": p["r_a"]}
    if m.model == "GENCLS":
        if "x'_d" not in p:
            raise ExportError(
                "ANDES's GENCLS needs x'_d, which the discovered classical model does not "
                'identify (no i_d, i_q lines): give it with assume={"x\'_d": value}'
            )
        machine = {"GENCLS": [{**common, "xd1": p["x'_d"], "xl": 0.0}]}
    elif m.model == "GENROU":
        xpp = p["x''_d"]
        machine = {
            "GENROU": [
                {
                    **common,
                    "xd": p["x_d"], "xq": p["x_q"], "xd1": p["x'_d"], "xq1": p["x'_q"],
                    "xd2": xpp, "xq2": xpp, "xl": p["x_l"],
                    "Td10": p["T'_d0"], "Tq10": p["T'_q0"],
                    "Td20": p["T''_d0"], "Tq20": p["T''_q0"],
                    "S10": p["S(1.0)"], "S12": p["S(1.2)"],
                }
            ]
        }  # fmt: skip
    else:
        raise ExportError(
            f"ANDES has no {m.model} (the {m.family} family's standard model): write the PSS/E "
            "record (format 'dyr') or the Python module (format 'py')"
        )
    bus = {"Vn": vn, "v0": 1.0, "a0": 0.0}
    volts = {"Vn1": vn, "Vn2": vn}
    case: dict[str, list[dict[str, Any]]] = {
        "Bus": [{"idx": 1, "name": "machine", **bus}, {"idx": 2, "name": "infinite", **bus}],
        "Line": [{"idx": "LINE1", "bus1": 1, "bus2": 2, "r": 0.0, "x": x_line, "b": 0.0, **volts}],
        "PV": [{"idx": "PV1", "bus": 1, "Vn": vn, "Sn": 100.0, "p0": p0, "v0": v0}],
        "Slack": [{"idx": "SLACK1", "bus": 2, "Vn": vn, "Sn": 100.0, "v0": 1.0, "a0": 0.0}],
        **machine,
    }
    if fault is not None:
        case["Fault"] = [
            {"idx": "FAULT1", "bus": 1, "tf": fault[0], "tc": fault[1], "xf": fault_x, "rf": 0.0}
        ]
    return case


# ----------------------------------------------------------------------------------------------
# the standard model fitted as a whole


PSAT_STATES = ("delta", "omega", "e_qp", "e_dp", "e_dpp")
"""The states of the PSAT 5.1 machine (and of its tied form, :func:`tied_source`)."""


def tied_source(report: PhysicalReport) -> str:
    """The PSAT 5.1 machine of ``report`` as a jaxdmd module (``model.py`` text) whose
    parameters are tied as the family ties them: one 1/M for P_m and P_e, one 1/T'_d0 for v_f
    and e'_q, one 1/T''_q0 for e'_d and e''_d, one pair (r_a, x'_d) / (r_a^2 + x'_d^2) for both
    stator lines, and P_e = e'_q i_q + e''_d i_d, Q_e = v_q i_d - v_d i_q from the same
    currents; Omega_b is the system's frequency where the report's is within 2 % of one
    (:data:`NOMINAL_HZ`). Its parameters start at the report's values (the first estimate of
    each; 1 where the report has none, as for a model that is not of the family, whose
    equations map only in part). Every line is linear in its parameters, so
    :func:`jaxdmd.physical.physical_parameters` reads it like a discovered model, and what a
    standard record holds is exactly this model."""

    def value(name: str) -> float:
        return _value(report, name) or 1.0

    d = report.get("D")
    damping = d is not None and d.note != "not in the model"
    m, xdp, ra = value("M"), value("x'_d"), _value(report, "r_a") or 0.0
    det = ra**2 + xdp**2
    de: list[float] = []

    def p(v: float) -> str:
        de.append(v)
        return f"p[{len(de) - 1}]"

    omega_b = _value(report, "Omega_b")
    nominal = min(NOMINAL_HZ, key=lambda f: abs(2 * math.pi * f / (omega_b or 1.0) - 1))
    if omega_b and abs(2 * math.pi * nominal / omega_b - 1) <= 0.02:
        speed = repr(2 * math.pi * nominal)  # the system's frequency: known, not fitted
    else:
        speed = p(omega_b or 1.0)
    swing = f"{p(1 / m)} * (P_m - P_e)" + (
        f" + {p(-(_value(report, 'D') or 0.0) / m)} * (omega - 1)" if damping else ""
    )
    t_d0, t_q0, t_q02 = value("T'_d0"), value("T'_q0"), value("T''_q0")
    x_d, x_q = value("x_d - x'_d"), value("x_q - x'_q - gamma_q")
    x_qp = value("x'_q - x'_d + gamma_q")
    d_axis = f"{p(1 / t_d0)} * (v_f - e_qp) + {p(-x_d / t_d0)} * i_d"
    q_axis = f"{p(-1 / t_q0)} * e_dp + {p(x_q / t_q0)} * i_q"
    q_fast = f"{p(1 / t_q02)} * (e_dp - e_dpp) + {p(x_qp / t_q02)} * i_q"
    vd, vq = "V * jnp.sin(delta - theta)", "V * jnp.cos(delta - theta)"
    i_d = f"p[0] * (e_dpp - {vd}) + p[1] * (e_qp - {vq})"
    i_q = f"p[0] * (e_qp - {vq}) - p[1] * (e_dpp - {vd})"
    lines = {
        "i_d": i_d,
        "i_q": i_q,
        "P_e": f"e_qp * ({i_q}) + e_dpp * ({i_d})",
        "Q_e": f"{vq} * ({i_d}) - {vd} * ({i_q})",
    }
    targets = list(lines)
    body = "\n".join(f"    {t}_ = {lines[t]}" for t in targets)
    return (
        f'"""The {report.family} machine, its parameters tied as the family ties them '
        '(jaxdmd.export.tied_source)."""\n\n'
        "import jax.numpy as jnp  # noqa: F401\n\n"
        "def equation(delta, omega, e_qp, e_dp, e_dpp, P_m, v_f, i_d, i_q, P_e, p):\n"
        f"    d_delta = {speed} * (omega - 1)\n"
        f"    d_omega = {swing}\n"
        f"    d_e_qp = {d_axis}\n"
        f"    d_e_dp = {q_axis}\n"
        f"    d_e_dpp = {q_fast}\n"
        "    return d_delta, d_omega, d_e_qp, d_e_dp, d_e_dpp\n\n"
        f"DE_PARAMS = {de!r}\n"
        "DE_TARGETS = ['delta', 'omega', 'e_qp', 'e_dp', 'e_dpp']\n\n"
        "def algebraic(delta, e_qp, e_dpp, V, theta, p):\n"
        f"{body}\n"
        f"    return {', '.join(t + '_' for t in targets)}\n\n"
        f"AE_PARAMS = {[ra / det, xdp / det]!r}\n"
        f"AE_TARGETS = {targets!r}\n"
    )


@dataclass(frozen=True)
class StandardFit:
    """The standard model of a discovery with its parameters fitted as the family ties them.

    Attributes:
        model: the tied model (a :class:`jaxdmd.pipeline.Discovery`; ``model.module_source()``
            is what ``standard_model.py`` holds, and ``model.simulate`` is exactly what the
            standard record simulates).
        machine: the standard record's values (:func:`standard_machine` of ``model``).
        report: the refit by simulation (:func:`jaxdmd.simfit.refit_simulation`'s report:
            ``kept``, the left-out and in-sample errors), ``"from"``: ``"refit"`` or ``"least
            squares"`` (the equation-error fit, the refit not kept), and ``"projected"`` where
            the discovered equations were not all of the family's form (what they have that the
            record leaves out).
    """

    model: Any
    machine: StandardMachine
    report: dict[str, Any]


def _equation_error_fit(eqs: Any, data: Sequence[Any], targets: Mapping[str, list]) -> Any:
    """``eqs`` (lines linear in their parameters) fitted by least squares to ``targets``
    (per output, one array per recording of ``data``; an output without targets is left out),
    each output's residual scaled by its target's spread. Returns the equations refitted."""
    import jax

    sk = eqs.skeleton()
    variables = {n: np.concatenate([np.asarray(ds[n]) for ds in data]) for n in sk.arguments}
    rows = [j for j, t in enumerate(eqs.contract.targets) if t in targets]
    y = np.stack([np.concatenate(targets[eqs.contract.targets[j]]) for j in rows])

    def predict(p: Any) -> Any:
        return sk(variables, p)[np.asarray(rows)]

    p0 = np.zeros(len(eqs.params))
    offset = np.asarray(predict(p0))
    jac = np.asarray(jax.jacfwd(predict)(p0))  # exact: the lines are linear in p
    scale = 1.0 / np.maximum(np.std(y, axis=1, keepdims=True), 1e-12)
    a = (jac * scale[..., None]).reshape(-1, len(p0))
    b = ((y - offset) * scale).ravel()
    theta, *_ = np.linalg.lstsq(a, b, rcond=None)
    return dataclasses.replace(eqs, params=tuple(float(x) for x in theta))


JACKKNIFED = ("H", "D", "x_d", "x'_d", "x_q", "x'_q", "T'_d0", "T'_q0", "T''_q0", "r_a")
"""The physical parameters of PSAT 5.1 whose standard errors :func:`fit_standard` reports."""


def _jackknife(de: Any, ae: Any, folds: Sequence[Sequence[float]]) -> dict[str, float]:
    """The delete-one jackknife standard error of each of :data:`JACKKNIFED` (its spread over
    the fits with one recording, or time block, left out: sqrt((n - 1)/n sum (v_i -
    mean)^2)); a parameter that does not vary (D where the model has none) is left out. It
    measures how the estimate moves between recordings, not a bias all of them share (of the
    state estimate, of the integration): on generator 31 of the benchmark the fitted values
    were 1-4 of these standard errors off the machine's."""
    n_de = len(de.params)
    values: list[dict[str, float]] = []
    for theta in folds:
        if not np.all(np.isfinite(theta)):
            return {}
        report = physical_parameters(
            dataclasses.replace(de, params=tuple(theta[:n_de])),
            dataclasses.replace(ae, params=tuple(theta[n_de:])),
        )
        row = {p.name: float(p.value) for p in report.parameters}
        row["x_d"] = row.get("x'_d", np.nan) + row.get("x_d - x'_d", np.nan)
        values.append(row)
    if len(values) < 2:
        return {}
    n = len(values)
    out: dict[str, float] = {}
    for name in JACKKNIFED:
        v = np.array([row.get(name, np.nan) for row in values])
        se = float(np.sqrt((n - 1) / n * np.sum((v - v.mean()) ** 2)))
        if np.isfinite(se) and se > 0:
            out[name] = se
    return out


def fit_standard(
    discovery: Any,
    train: Sequence[Any],
    *,
    played_from: Sequence[Any] | None = None,
    config: Any = None,
    assume: Mapping[str, float] | None = None,
) -> StandardFit:
    """The standard PSAT 5.1 machine (GENROU in the records) nearest to ``discovery``, its
    parameters tied as the family ties them (:func:`tied_source`) and fitted to the training
    recordings: first by least squares on the equations (the states smoothed with the
    discovered state equations, :func:`jaxdmd.refine.model_states`, their derivatives
    estimated; the measured algebraic variables), then together by how the model simulates
    the recordings (:func:`jaxdmd.simfit.refit_simulation`: closed and with the measured
    algebraic variables played in; kept where it simulates them better, its left-out error
    reported).

    A discovered model holds several estimates of one parameter (1/T'_d0 from v_f and from
    e'_q, each stator line its own reactance, a power line built from current and voltage
    lines of its own) and small stand-in terms; a standard record holds one value each and no
    stand-in. Read off the lines, the record then simulates differently from the discovered
    model and from the recordings. Fitted as a whole, its values are those with which the
    standard model itself simulates the recordings best. A discovery with PSAT 5.1's states
    whose equations are not all of the family's form (a stand-in term, a missing one) is
    projected on the family the same way; ``report["projected"]`` then says what the record
    leaves out. ``played_from``, ``config``: as for ``refit_simulation`` (``played_from``
    default: the model-smoothed recordings). Raises :class:`ExportError` where the states are
    not PSAT 5.1's or the recordings lack a channel the standard model needs."""
    from jaxdmd.pipeline import loads
    from jaxdmd.refine import model_states
    from jaxdmd.select import SelectionConfig
    from jaxdmd.simfit import refit_simulation

    states = tuple(discovery.de.contract.targets)
    if sorted(states) != sorted(PSAT_STATES):
        raise ExportError(
            f"a standard model is fitted for PSAT 5.1's states {list(PSAT_STATES)} only (this "
            f"model's: {list(states)}); export the record as identified or the module ('py')"
        )
    report = physical_parameters(discovery.de, getattr(discovery, "ae", None))
    try:
        standard_machine(report, assume)
        projected = None
    except ExportError as err:
        projected = str(err).split(": no standard record")[0]
    tied = loads(tied_source(report), "<tied standard model>")
    assert tied.ae is not None
    needed = {*tied.de.skeleton().arguments, *tied.ae.skeleton().arguments}
    missing = sorted(n for n in needed if any(n not in ds for ds in train))
    if missing:
        raise ExportError(f"the recordings lack {missing}, which the standard model needs")
    if played_from is None:  # initial states and played-in channels less noisy than measured
        try:
            played_from = [e.dataset for e in model_states(discovery.de, train)]
        except (ValueError, np.linalg.LinAlgError):
            played_from = list(train)
    smoothed = [ds.with_estimated_derivatives() for ds in played_from]
    de0 = _equation_error_fit(
        tied.de, smoothed, {s: [ds.derivative(s) for ds in smoothed] for s in PSAT_STATES}
    )
    regressors = [
        sm.with_values({n: ds[n] for n in ("V", "theta")})
        for sm, ds in zip(smoothed, train, strict=True)
    ]
    measured = {
        t: [np.asarray(ds[t]) for ds in train]
        for t in tied.ae.contract.targets
        if all(t in ds for ds in train)
    }
    ae0 = _equation_error_fit(tied.ae, regressors, measured)
    # the structure is the family's, fixed and small: its output-error fit is the better
    # estimator (consistent where the model is right), so it is kept wherever it simulates the
    # training recordings better; its left-out error is reported, not used as a guard
    config = dataclasses.replace(config or SelectionConfig(), tolerance=-1.0)
    de, ae, fit = refit_simulation(de0, ae0, train, played_from, config, fold_params=True)
    folds = fit.pop("fold_params", [])
    model = dataclasses.replace(tied, de=de, ae=ae, report={"standard_fit": fit})
    fit = {**fit, "from": "refit" if fit.get("kept") == "refit" else "least squares"}
    if fit["from"] == "refit":
        fit["stderr"] = _jackknife(de0, ae0, folds)
    if projected:
        fit["projected"] = projected
    machine = standard_machine(model, assume)
    how = (
        f"fitted by simulation to {len(train)} recording(s)"
        if fit["from"] == "refit"
        else f"fitted by least squares to {len(train)} recording(s) (the refit by simulation was "
        f"not kept: {fit.get('kept')})"
    )
    notes = [f"PSAT 5.1's parameters tied as the family ties them, {how}"]
    if fit.get("stderr"):
        notes.append(
            f"jackknife standard errors over the {len(folds)} left-out "
            f"{fit.get('held_out', 'folds')}: "
            + ", ".join(f"{k} {v:.3g}" for k, v in fit["stderr"].items())
        )
    if projected:
        notes.append(f"projected on PSAT 5.1: {projected}")
    machine = dataclasses.replace(machine, notes=(*notes, *machine.notes))
    return StandardFit(model, machine, fit)


# ----------------------------------------------------------------------------------------------
# the Python module and the folder


def write_module(discovery: Any, path: str | Path) -> Path:
    """Write the model as jaxdmd's Python module (``model.py``: the skeletons and their fitted
    parameters; any structure). ``jaxdmd.load(path).simulate(recording)`` rolls it out."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(discovery.module_source())
    return path


def _machine(
    discovery: Any,
    assume: Mapping[str, float] | None,
    fitted_to: Sequence[Any] | None,
    out: Path,
    written: dict[str, Any],
) -> StandardMachine | ExportError:
    """The standard record's values for :func:`export` (fitted where it can be), or why none."""
    try:
        if fitted_to:
            try:
                fit = fit_standard(discovery, fitted_to, assume=assume)
            except ExportError as err:  # no tied form for it: the record as read off
                written["standard_fit"] = {"from": "read off", "why": str(err)}
            else:
                written["standard_model"] = write_module(fit.model, out / "standard_model.py")
                written["standard_fit"] = fit.report
                return fit.machine
        return standard_machine(discovery, assume)
    except ExportError as err:
        return err


def export(
    discovery: Any,
    directory: str | Path,
    formats: Sequence[str] = FORMATS,
    *,
    bus: int = 1,
    machine_id: str = "1",
    assume: Mapping[str, float] | None = None,
    andes: Mapping[str, Any] | None = None,
    strict: bool = False,
    fitted_to: Sequence[Any] | None = None,
) -> dict[str, Any]:
    """Write ``discovery`` into ``directory`` in each of ``formats`` (``dyr``: ``model.dyr``,
    ``andes``: ``andes_case.json``, ``py``: ``model.py``).

    Returns ``{format: path}`` for what was written and ``{format: reason}`` for a format the
    model cannot be written in (with ``strict``, that raises :class:`ExportError` instead).
    ``andes``: keyword arguments of :func:`andes_case` (operating point, line, fault).
    ``fitted_to``: training recordings; the standard records then hold the standard model
    fitted as a whole to them (:func:`fit_standard`), which is also written as
    ``standard_model.py`` (``{"standard_model": path}``; ``{"standard_fit": report}``), and
    where no tied form exists the records are read off the discovered lines as without it.
    """
    unknown = [f for f in formats if f not in FORMATS]
    if unknown:
        raise ValueError(f"unknown export format(s) {unknown}; use some of {list(FORMATS)}")
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Any] = {}
    machine: StandardMachine | ExportError | None = None
    for fmt in formats:
        if fmt == "py":
            written[fmt] = write_module(discovery, out / "model.py")
            continue
        if machine is None:
            machine = _machine(discovery, assume, fitted_to, out, written)
        try:
            if isinstance(machine, ExportError):
                raise machine
            if fmt == "dyr":
                path = out / "model.dyr"
                path.write_text(dyr_record(machine, bus, machine_id))
            else:
                path = out / "andes_case.json"
                path.write_text(json.dumps(andes_case(machine, **dict(andes or {})), indent=1))
            written[fmt] = path
        except ExportError as err:
            if strict:
                raise
            written[fmt] = str(err)
    return written
