"""The data options shared by ``jaxdmd discover`` and ``jaxdmd diagnose``: channel roles on the
command line (``--states a,b --inputs u --algebraic x --boundary V,theta``, ``--role x=state``),
so that a CSV without a sidecar runs; the flags override or complete the roles a file carries
(a CSV's sidecar, an ``.npz``'s metadata)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from jaxdmd.data import (
    ROLES,
    DataError,
    Dataset,
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

ROLE_KEYS: tuple[str, ...] = ("states", "inputs", "algebraic", "boundary", "role")
"""The ``argparse`` destinations of the role flags (recorded in run.json)."""

HINT = "--states/--algebraic/--inputs/--boundary NAME or --role NAME=ROLE"


def add_role_arguments(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--states``, ``--inputs``, ``--algebraic``, ``--boundary`` (comma-separated column
    names, repeatable) and ``--role NAME=ROLE`` (repeatable)."""
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
    flags, and check that they can be fitted together.

    Without role flags this is `jaxdmd.data.load_many`. With them, every flag's column must be
    in every file, and every column must then have a role (errors name the file, the column and
    the flag to use).
    """
    flags = role_flags(args)
    datasets = []
    for path in paths:
        if not flags:
            datasets.append(Dataset.load(path))
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
        datasets.append(Dataset.load(path, roles=roles))
    check_compatible(datasets, paths)
    return datasets
