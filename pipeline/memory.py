"""Process memory readings (Linux /proc, with a portable fallback)."""

from __future__ import annotations

import resource


def reset_peak_rss() -> None:
    """Reset the kernel's peak-RSS mark (Linux: VmHWM) so the next reading covers what follows."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def peak_rss_mb() -> float:
    """Peak resident memory since the last reset (Linux), else since process start, in MiB."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
