"""Work that will not fit in memory is refused before it starts.

A phantom at 0.1 mm voxels, a mesh with 1 mm elements over a head-sized label
map, a reconstruction on a fine grid: each takes memory in proportion to a count
that is known before any work (voxels, elements). Running out mid-way ends in
the kernel's OOM killer or a ``MemoryError`` traceback after minutes of work;
here the caller estimates the bytes from that count and :func:`check_fits`
refuses the run with one line: the estimate in GB, what is available and how to
lower it (``fluo: error: voxel_mm: ... needs about 13.4 GB ...``).

What is available is the least of: the system's ``MemAvailable``
(``/proc/meminfo``), the room left under this process's cgroup limit, and the
room left under its ``RLIMIT_DATA`` / ``RLIMIT_AS`` (a test's or a batch
system's cap). Each estimate is a measured peak per unit (bytes per voxel, per
element) with its ratio to the real peak (``/usr/bin/time -v``) stated where it
is defined (docs/reliability.md, "Memory estimates").
"""

from __future__ import annotations

import os
import resource

from fluoguide.errors import FluoInputError

GB = 1e9


def _proc_bytes(path, key):
    """A size line of a ``/proc`` file (``MemAvailable`` of ``/proc/meminfo``,
    ``VmData`` of ``/proc/self/status``; kB there) in bytes, or None."""
    try:
        with open(path) as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _read_int(path):
    try:
        with open(path) as fh:
            text = fh.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _cgroup_room():
    """Bytes left under this process's cgroup memory limit, or None (no limit)."""
    try:
        with open("/proc/self/cgroup") as fh:
            lines = fh.read().splitlines()
    except OSError:
        return None
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        if parts[0] == "0" and parts[1] == "":                   # cgroup v2
            base = "/sys/fs/cgroup" + parts[2].rstrip("/")
            limit, used = _read_int(base + "/memory.max"), _read_int(base + "/memory.current")
        elif "memory" in parts[1].split(","):                    # cgroup v1
            base = "/sys/fs/cgroup/memory" + parts[2].rstrip("/")
            limit = _read_int(base + "/memory.limit_in_bytes")
            used = _read_int(base + "/memory.usage_in_bytes")
        else:
            continue
        # v1 says "no limit" with a huge number (2**63 rounded to a page)
        if limit is not None and used is not None and limit < 2**60:
            return max(0, limit - used)
    return None


def available_bytes():
    """Bytes this process can still take, or None where nothing can be read.

    Returns
    -------
    int or None
        min(MemAvailable, cgroup limit - usage, RLIMIT_DATA - VmData,
        RLIMIT_AS - VmSize) over the ones that exist (``/proc`` is Linux's:
        on other systems nothing is known and nothing is refused).
    """
    room = []
    avail = _proc_bytes("/proc/meminfo", "MemAvailable")           # Linux; elsewhere the limits alone
    if avail is not None:
        room.append(avail)
    cg = _cgroup_room()
    if cg is not None:
        room.append(cg)
    for limit_id, key in ((resource.RLIMIT_DATA, "VmData"), (resource.RLIMIT_AS, "VmSize")):
        soft, _ = resource.getrlimit(limit_id)
        used = _proc_bytes("/proc/self/status", key)
        if soft != resource.RLIM_INFINITY and used is not None:
            room.append(max(0, soft - used))
    return min(room) if room else None


def refuse(need_bytes, what, file=None, field=None, value=None, hint="", available=None):
    """Raise the one-line refusal for work of ``need_bytes`` (see :func:`check_fits`)."""
    avail = available_bytes() if available is None else available
    have = "" if avail is None else f", {avail / GB:.1f} GB are available"
    raise FluoInputError(f"{what} needs about {need_bytes / GB:.1f} GB of memory{have}"
                         + (f": {hint}" if hint else ""), file=file, field=field, value=value)


def check_fits(need_bytes, what, hint, file=None, field=None, value=None):
    """Refuse work whose estimated peak does not fit in what is available.

    Parameters
    ----------
    need_bytes : float
        The estimated peak [bytes] the work adds to this process.
    what : str
        The work, for the message (``"the cylinder-tube phantom at 0.1 mm"``).
    hint : str
        How to lower it (``"use --voxel-mm 0.25 or more (about 1.1 GB)"``).
    file, field, value : optional
        What the message names (the option that sets the size and its value).

    Raises
    ------
    FluoInputError
        When ``need_bytes`` exceeds :func:`available_bytes`; nothing is checked
        where that cannot be read (not Linux).
    """
    if os.environ.get("FLUO_MEMORY_CHECK") == "0":
        return                  # an expert's override, e.g. for swap the kernel does not count
    avail = available_bytes()
    if avail is not None and need_bytes > avail:
        refuse(need_bytes, what, file=file, field=field, value=value, hint=hint, available=avail)


def peak_resident_bytes():
    """This process's peak resident memory so far [bytes] (``VmHWM``: what
    ``/usr/bin/time -v`` reports as its maximum resident set), or None where
    the system does not say."""
    hwm = _proc_bytes("/proc/self/status", "VmHWM")
    if hwm is not None:
        return hwm
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if not peak:
        return None
    import sys

    return int(peak) if sys.platform == "darwin" else int(peak) * 1024   # bytes / kB


#: blocks from this size [bytes] are mapped on their own and handed back to the
#: system when freed (glibc's M_MMAP_THRESHOLD), and the heap's free top is given
#: back above twice that (M_TRIM_THRESHOLD)
LARGE_BLOCK_BYTES = 16 << 20


def hand_back_large_blocks(threshold=LARGE_BLOCK_BYTES):
    """Make glibc return freed blocks of ``threshold`` bytes and more to the system
    at once; returns whether it was set (False off glibc, where nothing changes).

    glibc's default raises its mapping threshold to the size of each mapped block
    freed (up to 32 MiB), so after the first 20-30 MB arrays come and go (fields,
    factor workspaces) later ones are carved from the heap and its pages stay with
    the process: the peak resident memory then counts arrays long freed. The CLI
    fixes it at 16 MiB: lower thresholds saved a little more and paid for it in page
    faults (docs/changelog.md, 2026-11-30, measures both). Dask workers take 64 MiB
    (``runs.engine.prepare_worker``)."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3          # glibc malloc.h
        return bool(libc.mallopt(m_mmap_threshold, int(threshold))
                    and libc.mallopt(m_trim_threshold, 2 * int(threshold)))
    except (OSError, AttributeError):
        return False
