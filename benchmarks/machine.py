"""Which machine a benchmark ran on: the one line every script's results carry under "machine"."""

from __future__ import annotations

import os
import platform
from pathlib import Path


def describe_machine(gpu: str | None = None) -> str:
    """CPU model, core count and Python version (and ``gpu``'s name), for the line that says where the table
    was measured."""
    model = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        names = [line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines() if line.startswith("model name")]
        model = names[0] if names else model
    return f"{model}, {os.cpu_count()} cores, Python {platform.python_version()}" + (f", {gpu}" if gpu else "")
