"""What this process knows about its CPU, for the kernels' build flags and the numerics' fingerprint."""
from __future__ import annotations

import functools
import platform


@functools.cache
def cpu_info() -> tuple[str, str, frozenset[str]]:
    """(vendor, model name, flags) from /proc/cpuinfo (empty where it does not exist)."""
    vendor, model, flags = platform.machine(), platform.processor() or platform.machine(), frozenset()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                key, _, value = line.partition(":")
                key, value = key.strip(), value.strip()
                if key == "vendor_id":
                    vendor = value
                elif key == "model name":
                    model = value
                elif key == "flags":
                    flags = frozenset(value.split())
                    break
    except OSError:
        pass
    return vendor, model, flags


def cpu_flags() -> frozenset[str]:
    """The CPU's feature flags (empty where /proc/cpuinfo does not exist)."""
    return cpu_info()[2]
