"""One vocabulary of flags (README, "Flags"): the words shared by several commands, and the
old spellings kept as hidden aliases (argparse.SUPPRESS) so that scripts keep working."""

from __future__ import annotations

import argparse

JSON_HELP = "print exactly one JSON object on stdout"
#: the default random seed of every command that draws random numbers (demo, sim, plan)
DEFAULT_SEED = 0


def add_json(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help=JSON_HELP)


def add_seed(parser: argparse.ArgumentParser, what: str = "random seed") -> None:
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help=f"{what} (default {DEFAULT_SEED})")


def add_aliased(parser, name: str, old: str, **kwargs) -> None:
    """``name`` with its help; ``old`` the same option, accepted but not listed."""
    dest = kwargs.pop("dest", None) or name.lstrip("-").replace("-", "_")
    parser.add_argument(name, dest=dest, **kwargs)
    hidden = {k: v for k, v in kwargs.items() if k in ("type", "metavar", "choices", "action")}
    parser.add_argument(old, dest=dest, help=argparse.SUPPRESS, default=argparse.SUPPRESS, **hidden)
