"""Subcommands of the ``adnmesh`` command line, one module each.

A command module exposes

``add_parser(subparsers) -> argparse.ArgumentParser``
    Add its subparser (``subparsers.add_parser(NAME, help=...)``) with its arguments and return it.
``run(args: argparse.Namespace) -> int``
    Do the work and return the exit code (0 success). Raise
    :class:`~adnmesh.errors.ConfigError` or :class:`~adnmesh.errors.UsageError` for user errors;
    :func:`adnmesh.cli.main` prints them as one line and exits with code 2.

To add a command, write ``adnmesh/commands/<name>.py`` and list it in ``adnmesh.cli.COMMAND_NAMES``.
"""

import argparse
import os
import stat
from pathlib import Path

from adnmesh.errors import UsageError
from adnmesh.files import check_writable

__all__ = ["add_config_argument", "add_quantity_argument", "certificate_directory",
           "check_run_limits", "input_file", "load_loop_config", "output_path"]


def add_config_argument(parser: argparse.ArgumentParser) -> None:
    """Add the positional ``CONFIG`` argument (path of a YAML config file) to ``parser``."""
    parser.add_argument(
        "config", metavar="CONFIG", help="configuration file (YAML), e.g. configs/simbench.yaml"
    )


def add_quantity_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--quantity p|q``: which loop a numeric command works on."""
    parser.add_argument(
        "--quantity", choices=("p", "q"), default="p",
        help="the loop: p active power (default) or q reactive power (each DER's reactive "
        "range as its C_d, its reactive dynamics; docs/method.md#reactive-power)")


def load_loop_config(args: argparse.Namespace):
    """The config of ``args.config`` for the loop ``args.quantity``: as written for P, its
    reactive view for Q (:func:`adnmesh.reactive.reactive_view`)."""
    from adnmesh.config import load_config

    config = load_config(args.config)
    if getattr(args, "quantity", "p") == "q":
        from adnmesh.reactive import reactive_view
        config = reactive_view(config)
    return config


def input_file(path: str | Path) -> Path:
    """``path`` of an input file (a recording), refused in one line if it is there but not a
    regular file or folder: a FIFO would block the reader until something writes to it, a
    device such as ``/dev/zero`` never ends. A missing file is left to the reader to say."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return Path(path)
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        kind = "a FIFO" if stat.S_ISFIFO(mode) else "a device or socket"
        raise UsageError(f"{path}: not a regular file ({kind})")
    return Path(path)


def output_path(path: str | Path, flag: str, directory: bool = False) -> Path:
    """``path`` of the output ``flag`` asks for, checked before any work
    (:func:`adnmesh.files.check_writable`: parent folders made, a test file written and
    removed); a one-line :class:`~adnmesh.errors.UsageError` if it cannot be written there."""
    try:
        return check_writable(path, directory)
    except OSError as exc:
        where = "" if exc.filename in (None, str(path)) else f" ({exc.filename})"
        what = "folder" if directory else "file"
        raise UsageError(f"{flag} {path}: cannot write the {what} there: "
                         f"{exc.strerror or exc}{where}") from None


def comma_list(text: str | None) -> list[str]:
    """The items of a comma-separated option value, stripped, empty ones dropped (``None``:
    none). The one parser of every such option (``--ders``, ``--solution-space``,
    ``--external``, ``--routers``, ``--renew``, ``--only``, ...)."""
    return [item.strip() for item in (text or "").split(",") if item.strip()]


def der_id_list(config, text: str, option: str) -> list[str]:
    """DER ids of ``config`` from a comma-separated ``option`` value, as given; one line for
    none, a duplicate or an unknown id."""
    ids = comma_list(text)
    if not ids:
        raise UsageError(f"{option}: give at least one DER id, e.g. SGen1,SGen5")
    if len(set(ids)) != len(ids):
        raise UsageError(f"{option}: duplicate DER id in {text!r}")
    known = config.der_ids()
    unknown = [i for i in ids if i not in known]
    if unknown:
        raise UsageError(f"{option}: unknown DER id '{unknown[0]}' (known: {', '.join(known)})")
    return ids


def certificate_directory(args: argparse.Namespace) -> Path | None:
    """``up``'s certificate directory of the secure profile (``--secure``/``--certs``;
    checked: it holds ``up``'s certificate), or None (open profile); the ``--listen``
    endpoint must fit the profile."""
    from adnmesh.runtime.identity import cert_files
    from adnmesh.runtime.security import check_endpoints

    secure = bool(args.secure or args.certs)
    check_endpoints([args.listen] if args.listen else [], secure, flag="--listen")
    if not secure:
        return None
    certs = Path(args.certs or "certs")
    if not certs.is_dir():
        raise UsageError(f"{certs}: no certificate directory; create it with 'adnmesh certs "
                         f"{certs} --config {args.config}'")
    cert_files(certs, "up").check()
    return certs.resolve()


def check_run_limits(args: argparse.Namespace) -> None:
    """``up``'s ``--seed``, ``--startup-timeout`` and ``--stall-timeout`` (s) in their ranges
    (one grid's run or a hierarchy's); else a one-line :class:`UsageError`."""
    if args.seed is not None and not 0 <= args.seed < 2**63:
        raise UsageError(f"--seed must be in [0, 2**63), got {args.seed}")
    if args.startup_timeout is not None and not 0 < args.startup_timeout <= 86400:
        raise UsageError(f"--startup-timeout must be in (0, 86400] s, got "
                         f"{args.startup_timeout:g}")
    if not 0 <= args.stall_timeout <= 86400:
        raise UsageError(f"--stall-timeout must be in [0, 86400] s, got {args.stall_timeout:g}")
