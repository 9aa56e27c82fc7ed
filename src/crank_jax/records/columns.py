"""The columns of a record: what names a column may have, and the rule that every column
plays exactly one role.

A record's columns each play one role: the time, a channel (the angle or another sensor
reading), the slider force P, the crank torque tau, or a load's input. A column read in
two roles (an angle column named `tau` read as the angle *and* as the torque) would
silently drive the model with the data it is fitted to, so every reading path
([`load_data`][crank_jax.records.data.load_data], [`Data`][crank_jax.records.data.Data],
[`Scene`][crank_jax.scene.Scene]) asks [`role_conflict`][] before it uses the names.
"""

from __future__ import annotations

from collections.abc import Iterable

__all__ = ["column_problem", "role_conflict", "RESERVED", "TIME_ROLE", "load_roles"]

#: The columns [`save_data`][crank_jax.records.data.save_data] and `crank-jax synth` write
#: for the time and the known loads; a sensor or a load's input may not take these names.
RESERVED: dict[str, str] = {"t": "the time column t", "P": "the slider force column P",
                            "tau": "the crank torque column tau"}


def column_problem(name) -> str | None:
    """Why `name` cannot be a column of a record written as CSV, or None when it can.

    A column name must be a non-empty string without a comma or a double quote (the
    CSV's separator and quote), without control characters (a newline would split the
    header), and without spaces at either end (a reader strips them, so it would never
    be found again)."""
    if not isinstance(name, str):
        return f"must be a string (a column name), got {type(name).__name__} {name!r}"
    if not name:
        return "must be a non-empty column name"
    if name != name.strip():
        return f"{name!r} has spaces at an end; remove them"
    if "," in name or '"' in name:
        return f"{name!r} holds a comma or a double quote (CSV's separator and quote); " \
               "rename the column"
    if not name.isprintable():
        return f"{name!r} holds a control character (a newline, a tab); rename the column"
    return None


def role_conflict(claims: Iterable[tuple[str, str]]) -> str | None:
    """The first column claimed for two roles, as a message naming both, or None.

    `claims`: (column, role) pairs, the role in words (e.g. ``"channel phi (`sensors=`)"``);
    the same (column, role) twice is one claim."""
    seen: dict[str, str] = {}
    for column, role in claims:
        if column in seen and seen[column] != role:
            return (f"column {column!r} is claimed twice, as {seen[column]} and as {role}; "
                    "every column has one role: rename one of them")
        seen.setdefault(column, role)
    return None


#: The role of a file's time column (`t_col`, the CLI's `--t-col`).
TIME_ROLE = "the time (`t_col=`)"


def load_roles(P_col: str, tau_col: str) -> list[tuple[str, str]]:
    """The roles of a file's load columns (read whenever its header has them)."""
    return [(P_col, f"the slider force P (the load column {P_col!r})"),
            (tau_col, f"the crank torque tau (the load column {tau_col!r})")]
