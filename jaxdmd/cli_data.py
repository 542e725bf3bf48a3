"""The data options shared by ``jaxdmd discover`` and ``jaxdmd diagnose``: channel roles on the
command line (``--states a,b --inputs u --algebraic x --boundary V,theta``, ``--role x=state``),
so that a CSV without a sidecar runs; the flags override or complete the roles a file carries
(a CSV's sidecar, an ``.npz``'s metadata). ``--events T1,T2`` replaces the files' event times
(fault on, fault clear)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from jaxdmd.data import (
    ROLES,
    DataError,
    Dataset,
    _check_events,
    check_compatible,
    data_columns,
    stored_roles,
)

ROLE_FLAGS: dict[str, str] = {
    "state": "--states",
    "input": "--inputs",
    "algebraic": "--algebraic",
    "boundary": "--boundary",
}
"""The flag naming the columns of each role."""

ROLE_KEYS: tuple[str, ...] = ("states", "inputs", "algebraic", "boundary", "role", "events")
"""The ``argparse`` destinations of the data options, the role flags and ``--events`` (recorded
in run.json)."""

HINT = "--states/--algebraic/--inputs/--boundary NAME or --role NAME=ROLE"


def add_role_arguments(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--states``, ``--inputs``, ``--algebraic``, ``--boundary`` (comma-separated column
    names, repeatable), ``--role NAME=ROLE`` (repeatable) and ``--events T1,T2``."""
    what = {
        "state": "state columns (fitted d/dt equations)",
        "input": "input columns (played in)",
        "algebraic": "algebraic columns (AE equations)",
        "boundary": "boundary columns (network side, played in)",
    }
    for role, flag in ROLE_FLAGS.items():
        parser.add_argument(
            flag,
            action="append",
            metavar="A,B",
            help=f"{what[role]}, comma-separated; override or complete the file's sidecar",
        )
    parser.add_argument(
        "--role",
        action="append",
        metavar="NAME=ROLE",
        help=f"a column's role, one of {', '.join(ROLES)} (repeatable)",
    )
    parser.add_argument(
        "--events",
        metavar="T1,T2",
        help="times of known discontinuities (fault on, fault clear) in seconds, "
        "comma-separated; replace the files' events ('' for none)",
    )


def parse_events(args: argparse.Namespace) -> tuple[float, ...] | None:
    """The times of ``--events``, sorted (None when it is not given; ``''`` gives none).

    Raises:
        DataError: naming ``--events`` and its value, for an entry that is not a finite number.
    """
    value = getattr(args, "events", None)
    if value is None:
        return None
    times = []
    for item in value.split(",") if value.strip() else []:
        try:
            times.append(float(item))
        except ValueError:
            raise DataError(
                f"--events {value!r}: {item.strip()!r} is not a time in seconds; give the "
                "times comma-separated, e.g. --events 1.0,1.1"
            ) from None
    try:
        return _check_events(times)
    except DataError as err:
        raise DataError(f"--events {value!r}: {err}") from None


def role_flags(args: argparse.Namespace) -> dict[str, tuple[str, str]]:
    """Column -> (role, the flag that named it), from the parsed role flags.

    Raises:
        DataError: a ``--role`` that is not ``NAME=ROLE`` with a known role, an empty name, or
            a column given two different roles.
    """
    out: dict[str, tuple[str, str]] = {}

    def put(name: str, role: str, flag: str) -> None:
        name = name.strip()
        if not name:
            raise DataError(f"{flag}: an empty column name")
        if name in out and out[name][0] != role:
            raise DataError(
                f"column {name!r} is given two roles: {out[name][0]} ({out[name][1]}) and "
                f"{role} ({flag})"
            )
        out[name] = (role, flag)

    for role, flag in ROLE_FLAGS.items():
        for value in getattr(args, flag[2:], None) or []:
            for name in value.split(","):
                put(name, role, flag)
    for value in getattr(args, "role", None) or []:
        name, sep, role = value.partition("=")
        role = role.strip()
        if not sep or role not in ROLES:
            raise DataError(
                f"--role {value!r}: expected NAME=ROLE with ROLE one of {', '.join(ROLES)}"
            )
        put(name, role, "--role")
    return out


def load_data(paths: Sequence[str | Path], args: argparse.Namespace) -> list[Dataset]:
    """Load recordings with the roles of their files, overridden or completed by the role
    flags, and with the events of ``--events`` in place of theirs; check that they can be
    fitted together.

    Without role flags and ``--events`` this is `jaxdmd.data.load_many`. With role flags, every
    flag's column must be in every file, and every column must then have a role (errors name
    the file, the column and the flag to use). The ``--events`` are given to
    `jaxdmd.data.Dataset.load`, so estimated derivatives are split at them and derivatives a
    file stores (``d/dt`` columns, an ``.npz``) are kept; every event must lie in every
    recording's time span.
    """
    flags = role_flags(args)
    events = parse_events(args)
    datasets = []
    for path in paths:
        if not flags:
            datasets.append(Dataset.load(path, events=events))
            continue
        if not Path(path).is_file():
            datasets.append(Dataset.load(path))  # its own error: not found, a directory
            continue
        try:
            columns = data_columns(path)
            roles = stored_roles(path)
        except (OSError, KeyError, ValueError) as err:  # DataError is a ValueError
            if isinstance(err, DataError):
                raise
            raise DataError(f"{path}: cannot be read as a jaxdmd dataset ({err})") from None
        for name in roles:
            if name not in columns:
                raise DataError(
                    f"{path}: its sidecar names column {name!r}, which the file lacks (its "
                    f"columns: {', '.join(columns)})"
                )
        for name, (_, flag) in flags.items():
            if name not in columns:
                raise DataError(
                    f"{path}: {flag} names column {name!r}, which the file lacks (its columns: "
                    f"{', '.join(columns)})"
                )
        roles.update({name: role for name, (role, _) in flags.items()})
        for name in columns:
            if name not in roles:
                raise DataError(
                    f"{path}: column {name!r} has no role; give it one with "
                    f"{HINT.replace('NAME', name)} (roles: {', '.join(ROLES)})"
                )
        datasets.append(Dataset.load(path, roles=roles, events=events))
    if events is not None:
        for path, ds in zip(paths, datasets, strict=True):
            try:
                _check_events(events, span=(float(ds.t[0]), float(ds.t[-1])))
            except DataError as err:
                raise DataError(f"{path}: --events {args.events!r}: {err}") from None
    check_compatible(datasets, paths)
    return datasets
