"""Option types and conventions shared by every ``c3bench`` command (:mod:`bench.cli`).

* :class:`Parser`: usage errors are one line, ``error: ...``, exit code 2;
* :func:`add_list` / :class:`ListAction`: list options take ``--x a b``, ``--x a,b`` and
  ``--x a --x b`` alike;
* :func:`positive_int`, :func:`nonnegative_int`, :func:`positive_float`: checked numbers;
* :func:`add_results`, :func:`add_executor`, :func:`add_quiet`: options with one meaning in
  every command.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 2, 130, 143
"""Exit codes: success, error (nothing to read, a failed command, cells left missing, a full
disk), bad input, interrupted (Ctrl-C), terminated (SIGTERM)."""


class Parser(argparse.ArgumentParser):
    """``argparse`` parser whose usage errors are one line, ``error: ...``, exit code 2."""

    def error(self, message: str) -> NoReturn:
        """Print ``error: message`` and exit with :data:`EXIT_USAGE`."""
        self.exit(EXIT_USAGE, f"error: {message} (see `{self.prog} --help`)\n")


def _number(convert: Callable[[str], Any], kind: str, low: float, strict: bool
            ) -> Callable[[str], Any]:
    """A type converting text with ``convert`` and rejecting values below ``low``."""

    def parse(text: str) -> Any:
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {kind}, got {text!r}") from None
        if not math.isfinite(value) or value < low or (strict and value == low):
            raise argparse.ArgumentTypeError(f"expected {kind}, got {text!r}")
        return value

    parse.__name__ = kind
    return parse


positive_int = _number(int, "an integer >= 1", 1, strict=False)
nonnegative_int = _number(int, "an integer >= 0", 0, strict=False)
positive_float = _number(float, "a finite number > 0", 0.0, strict=True)


def list_items(item: Callable[[str], Any] = str, choices: Sequence[str] | None = None
               ) -> Callable[[str], tuple[Any, ...]]:
    """A type reading one token as comma-separated items, each checked and converted."""

    def parse(text: str) -> tuple[Any, ...]:
        parts = [part.strip() for part in text.split(",") if part.strip()]
        if not parts:
            raise argparse.ArgumentTypeError(f"expected at least one value, got {text!r}")
        if choices is not None:
            for part in parts:
                if part not in choices:
                    raise argparse.ArgumentTypeError(
                        f"invalid choice {part!r} (choose from {', '.join(choices)})")
        return tuple(item(part) for part in parts)

    return parse


class ListAction(argparse.Action):
    """Collect a list option: ``--x a b``, ``--x a,b`` and ``--x a --x b`` give ``[a, b]``.

    Items keep their first-seen order and repeats are dropped; giving the option replaces its
    default.
    """

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        """Append the items of every token to the option's list."""
        current = getattr(namespace, self.dest, None)
        items = [] if current is None or current is self.default else list(current)
        for token in values:
            for value in token:
                if value not in items:
                    items.append(value)
        setattr(namespace, self.dest, items)


def add_list(parser: argparse.ArgumentParser, flag: str, *, metavar: str, help: str,
             item: Callable[[str], Any] = str, choices: Sequence[str] | None = None,
             default: Sequence[Any] | None = None, default_text: str | None = None) -> None:
    """Add a list option (:class:`ListAction`).

    ``help`` gets the accepted forms and the default appended: ``default_text``, else the
    default's items (nothing when there is none).
    """
    shown = default_text or ("" if not default else " ".join(map(str, default)))
    parser.add_argument(flag, nargs="+", action=ListAction, type=list_items(item, choices),
                        default=default, metavar=metavar,
                        help=f"{help} (space or comma separated"
                             + (f"; default: {shown})" if shown else ")"))


def add_results(parser: argparse.ArgumentParser, where: str) -> None:
    """Add ``--results ROOT``: the results root, with where this command reads or writes."""
    parser.add_argument("--results", default="results", metavar="ROOT",
                        help=f"results root (default: results); {where}")


def add_executor(parser: argparse.ArgumentParser, unit: str) -> None:
    """Add ``--jobs``, ``--scheduler`` and ``--rerun``."""
    parser.add_argument("--jobs", type=positive_int, default=2, metavar="N",
                        help="local worker processes (default: 2)")
    parser.add_argument("--scheduler", default=None, metavar="ADDR",
                        help=f"Dask scheduler address: run the {unit} on that cluster "
                             "(then --jobs is ignored)")
    parser.add_argument("--rerun", action="store_true",
                        help=f"run stored {unit} again (default: skip them)")


def add_quiet(parser: argparse.ArgumentParser) -> None:
    """Add ``--quiet``."""
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
