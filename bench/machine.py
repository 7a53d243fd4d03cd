"""The machine a measurement ran on: processor, host, cores, load, versions, time stamps.

The one place in ``bench/`` that asks the operating system about the machine; the runner's
``run_info.json`` (:func:`machine_info`) and the ``perf`` rows (:func:`host_label`,
:func:`affinity`, :func:`load_average`) both read it from here.
"""

from __future__ import annotations

import datetime as dt
import importlib.metadata as metadata
import math
import os
import platform
import socket
from pathlib import Path
from typing import Any

PACKAGES: tuple[str, ...] = ("c3bench", "numpy", "scipy", "pandas", "pyarrow", "matplotlib",
                             "dask", "distributed", "threadpoolctl", "mujoco")
"""Packages whose versions the report header lists."""


def utc_now() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def utc_stamp() -> str:
    """The current UTC time as a compact run id, ``YYYYmmddTHHMMSSZ``."""
    return dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")


def hostname() -> str:
    """The machine's network name."""
    return socket.gethostname()


def processor() -> str:
    """The processor's model name (``/proc/cpuinfo``), else what :mod:`platform` knows."""
    name = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return name


def host_label() -> str:
    """``host (processor, N cores)``: one text naming the machine (the ``perf`` rows)."""
    return f"{hostname()} ({processor()}, {os.cpu_count()} cores)"


def affinity() -> str:
    """The CPU cores this process may run on, comma separated (``all`` when unknown)."""
    try:
        return ",".join(str(core) for core in sorted(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return "all"


def load_average() -> float:
    """The 1-minute load average (NaN when the system does not report it)."""
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):
        return math.nan


def package_versions(names: tuple[str, ...] = PACKAGES) -> dict[str, str]:
    """Installed version of each package (``not installed`` when missing)."""
    versions = {}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def machine_info() -> dict[str, Any]:
    """Machine, Python and package versions for the report header (``run_info.json``)."""
    from c3bench.solvers.timing import blas_threads

    return {"cpu": processor(), "cores": os.cpu_count(), "host": hostname(),
            "platform": platform.platform(), "python": platform.python_version(),
            "packages": package_versions(), "blas_threads_default": blas_threads(),
            "blas_threads_timed": 1, "date": utc_now()}
