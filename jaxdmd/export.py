"""A discovered model written for other simulators (issue #18, item 3).

:func:`standard_machine` reads the machine-model family and the physical parameters of a
:class:`jaxdmd.pipeline.Discovery` (:func:`jaxdmd.physical.physical_parameters`) and names the
standard model they map to:

- ``classical`` -> **GENCLS** (H, D; in ANDES also x'_d, r_a, f_n): exact;
- ``one-axis`` -> **GENSAL** (PSS/E only; ANDES has no GENSAL);
- ``two-axis``, ``psat-5.1`` -> **GENROU**, with assumptions: a discovered model identifies no
  sub-transient d axis, no leakage reactance and no saturation, and GENROU has one sub-transient
  reactance for both axes (x''_d = x''_q). PSAT 5.1 puts x'_d in both stator lines (its x''_q is
  x'_d), which GENROU cannot take (X'_d - X''_d is one of its divisors): the record sets
  x''_d = x''_q = ``xpp_ratio`` x'_d (default 0.8) and a fast T''_d0 (default 0.03 s);
  every assumed value is listed in the record's comment (:data:`ASSUMED`, ``assume=`` overrides).

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
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from jaxdmd.physical import PhysicalReport, physical_parameters

__all__ = [
    "ASSUMED",
    "FORMATS",
    "ExportError",
    "StandardMachine",
    "andes_case",
    "dyr_record",
    "export",
    "standard_machine",
    "write_module",
]

FORMATS = ("dyr", "andes", "py")

ASSUMED: dict[str, float] = {
    "T''_d0": 0.03,  # s, a fast d-axis sub-transient circuit (not in the discovered models)
    "T''_q0": 0.05,  # s, GENSAL's q axis (one-axis: no q-axis dynamics identified)
    "xpp_ratio": 0.8,  # x''_d = x''_q = xpp_ratio x'_d
    "x_l": 0.0,  # pu, leakage reactance (not identified)
    "S(1.0)": 0.0,  # saturation (not identified)
    "S(1.2)": 0.0,
}
"""Values a discovered model does not identify and GENSAL/GENROU need (``assume=`` replaces
any of them; ``x''_d`` may be given instead of ``xpp_ratio``)."""


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
    notes: list[str] = []

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
    else:
        need("T'_q0")
        if family == "two-axis":
            values["x_q"] = need("x'_q") + need("x_q - x'_q")
            assumed_value("T''_q0")
        else:  # psat-5.1
            need("x_q")
            need("x'_q")
            need("T''_q0")
            notes.append(
                "PSAT 5.1 uses x'_d as its sub-transient q-axis reactance and has no d-axis "
                "sub-transient circuit; GENROU needs x''_d < x'_d"
            )
        assumed_value("T''_d0")
    if "x''_d" in assume:
        values["x''_d"] = float(assume["x''_d"])
    else:
        values["x''_d"] = assumed_value("xpp_ratio") * xdp
    assumed.append("x''_d")
    for name in ("x_l", "S(1.0)", "S(1.2)"):
        assumed_value(name)
    model = "GENSAL" if family == "one-axis" else "GENROU"
    return StandardMachine(family, model, values, tuple(assumed), tuple(notes), report)


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
# the Python module and the folder


def write_module(discovery: Any, path: str | Path) -> Path:
    """Write the model as jaxdmd's Python module (``model.py``: the skeletons and their fitted
    parameters; any structure). ``jaxdmd.load(path).simulate(recording)`` rolls it out."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(discovery.module_source())
    return path


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
) -> dict[str, Path | str]:
    """Write ``discovery`` into ``directory`` in each of ``formats`` (``dyr``: ``model.dyr``,
    ``andes``: ``andes_case.json``, ``py``: ``model.py``).

    Returns ``{format: path}`` for what was written and ``{format: reason}`` for a format the
    model cannot be written in (with ``strict``, that raises :class:`ExportError` instead).
    ``andes``: keyword arguments of :func:`andes_case` (operating point, line, fault).
    """
    unknown = [f for f in formats if f not in FORMATS]
    if unknown:
        raise ValueError(f"unknown export format(s) {unknown}; use some of {list(FORMATS)}")
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path | str] = {}
    machine: StandardMachine | ExportError | None = None
    for fmt in formats:
        if fmt == "py":
            written[fmt] = write_module(discovery, out / "model.py")
            continue
        if machine is None:
            try:
                machine = standard_machine(discovery, assume)
            except ExportError as err:
                machine = err
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
