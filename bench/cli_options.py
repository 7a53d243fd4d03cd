"""Option types and conventions shared by every ``c3bench`` command (:mod:`bench.cli`).

* :class:`Parser`: usage errors are one line, ``error: ...``, exit code 2;
* :func:`add_list` / :class:`ListAction`: list options take ``--x a b``, ``--x a,b`` and
  ``--x a --x b`` alike;
* :func:`positive_int`, :func:`nonnegative_int`, :func:`positive_float`: checked numbers;
  :data:`OPTION_CAPS`: the largest value of a count option, whichever command has it
  (:class:`Parser` applies it: a huge value is a usage error, not a run that hangs or runs
  out of memory);
* :func:`path_text`: a path option's text (not empty or blank);
* :func:`add_results`, :func:`add_executor`, :func:`add_quiet`: options with one meaning in
  every command.
"""

from __future__ import annotations

import argparse
import enum
import math
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 2, 130, 143
"""Exit codes: success, error (nothing to read, a failed command, cells left missing, a full
disk), bad input, interrupted (Ctrl-C), terminated (SIGTERM)."""


MAX_SAMPLES = 4096
"""Most model samples (``--samples`` of ``perf``, ``closed-loop``, ``closed-loop-trials``):
the GPU measurements use 1024 and 4096. The stacked ``c3plus-robust`` controller takes fewer
(:data:`bench.cli_checks.MAX_STACKED_SAMPLES`)."""
MAX_ITERATIONS = 1000
"""Most ADMM iterations per control step (``--iterations`` of ``perf`` and ``closed-loop``;
default 10): the geometric schedule's ``rho = 50 * 2^i`` overflows float64 past about 1018."""
MAX_TRIALS = 10_000
"""Most randomized trials (``--trials`` of ``closed-loop-trials`` and ``closed-loop-suite``;
the full suite runs 100)."""
OPTION_CAPS: dict[str, int] = {"--samples": MAX_SAMPLES, "--iterations": MAX_ITERATIONS,
                               "--trials": MAX_TRIALS}
"""The largest value of each count option, in every command that has it (:class:`Parser`)."""


_HELP_PROG = "_help_prog"
"""Namespace attribute naming the command whose help a usage error points at."""


def parse_command(parser: argparse.ArgumentParser, arguments: list[str]) -> argparse.Namespace:
    """``parser.parse_args(arguments)``, with unrecognised arguments pointing at the help of
    the command they were given to (``c3bench run --help``, not ``c3bench --help``)."""
    parsed, extras = parser.parse_known_args(arguments)
    if extras:
        prog = getattr(parsed, _HELP_PROG, parser.prog)
        parser.exit(EXIT_USAGE, f"error: unrecognized arguments: {' '.join(extras)} "
                                f"(see `{prog} --help`)\n")
    return parsed


class Parser(argparse.ArgumentParser):
    """``argparse`` parser whose usage errors are one line, ``error: ...``, exit code 2.

    Its subparsers are of this class too. :meth:`add_argument` caps the options of
    :data:`OPTION_CAPS` and lists enumeration choices by their values (never an enum's
    ``repr``).
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.set_defaults(**{_HELP_PROG: self.prog})  # the innermost command's wins

    def add_argument(self, *args: Any, **kwargs: Any) -> argparse.Action:
        """``argparse``'s, with an option of :data:`OPTION_CAPS` capped (its type checks the
        cap, its help states it) and ``choices`` of enumeration members given as values."""
        cap = next((OPTION_CAPS[flag] for flag in args if flag in OPTION_CAPS), None)
        if cap is not None and kwargs.get("type") is not None:
            each = kwargs.get("nargs") in ("+", "*")
            kwargs["type"] = at_most(kwargs["type"], cap)
            kwargs["help"] = _with_cap(kwargs.get("help"), cap, each)
        if kwargs.get("choices") is not None:
            kwargs["choices"] = plain_choices(kwargs["choices"])
        return super().add_argument(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        """Print ``error: message`` and exit with :data:`EXIT_USAGE`."""
        self.exit(EXIT_USAGE, f"error: {message} (see `{self.prog} --help`)\n")


def plain_choices(choices: Any) -> Any:
    """``choices`` with enumeration members replaced by their values (so that a usage error
    lists ``geometric``, not ``<RhoScheduleName.GEOMETRIC: 'geometric'>``)."""
    if isinstance(choices, str) or not isinstance(choices, Sequence | set | frozenset):
        return choices
    if not any(isinstance(choice, enum.Enum) for choice in choices):
        return choices
    return tuple(choice.value if isinstance(choice, enum.Enum) else choice
                 for choice in choices)


def at_most(convert: Callable[[str], Any], cap: int) -> Callable[[str], Any]:
    """``convert``, then a check that the number (or every number of a tuple) is at most
    ``cap``; a usage error saying so otherwise."""

    def parse(text: str) -> Any:
        value = convert(text)
        numbers = value if isinstance(value, tuple) else (value,)
        if any(number > cap for number in numbers):
            raise argparse.ArgumentTypeError(f"expected at most {cap}, got {text!r}")
        return value

    parse.__name__ = getattr(convert, "__name__", "value")
    return parse


def _with_cap(help: str | None, cap: int, each: bool) -> str | None:
    """``help`` stating the cap: inside its closing parenthesis when it ends with one."""
    if help is None or help == argparse.SUPPRESS:
        return help
    words = f"{'each ' if each else ''}at most {cap}"
    return f"{help[:-1]}; {words})" if help.endswith(")") else f"{help} ({words})"


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


def path_text(text: str) -> str:
    """A path option's text: not empty or blank (an empty path would silently mean the
    current directory)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a path, got an empty one ({text!r})")
    return text


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
    parser.add_argument("--results", type=path_text, default="results", metavar="ROOT",
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
