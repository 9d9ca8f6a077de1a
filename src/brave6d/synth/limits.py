"""``brave6d synth``'s bounds, one set for the flags (``brave6d.synth.cli``) and the API (``SynthOptions``),
and the start-up checks of what the machine can hold.

One image costs the CPU renderer (capture's ``SimCamera`` over a ``SceneModel``, the effects, the
silhouettes and masks, the PNG encoding) about 400 bytes per pixel at its peak, on top of the
~380 MiB a worker process holds with the library loaded (peak RSS measured at 128x96 .. 2560x1920,
1 to 5 objects, with and without effects: 382 .. 407 B/pixel). ``render_memory_bytes`` estimates
with a margin over that. A side of ``MAX_SIDE`` (4096 pixels, 16.8 Mpixels) needs about 7.5 GiB
per worker; BOP images are 640x480 .. 1920x1080 (0.5 GiB .. 1.3 GiB).
"""

from __future__ import annotations

import logging
import os
from numbers import Integral
from pathlib import Path

from brave6d.core.cli_types import Bound
from brave6d.core.errors import BraveError

log = logging.getLogger(__name__)

MIN_SIDE = 8
MAX_SIDE = 4096
MAX_IMAGES = 1_000_000
MAX_SEED = 2 ** 63 - 1
MAX_WORKERS = 1024
#: Workers per usable CPU core beyond which ``--workers`` is refused (above one per core: a warning).
OVERSUBSCRIPTION = 4

#: option/flag name -> its range (``brave6d.synth.cli`` parses the flags with them, ``SynthOptions`` checks them).
BOUNDS: dict[str, Bound] = {"images": Bound(1, MAX_IMAGES, integer=True), "seed": Bound(0, MAX_SEED, integer=True),
                            "workers": Bound(1, MAX_WORKERS, integer=True),
                            "width": Bound(MIN_SIDE, MAX_SIDE, integer=True),
                            "height": Bound(MIN_SIDE, MAX_SIDE, integer=True)}

#: Peak memory of rendering one image, per pixel (measured 382 .. 407) and per worker process
#: (measured ~380 MiB); both with a margin.
BYTES_PER_PIXEL = 450
PROCESS_BYTES = 448 * 2 ** 20

GIB = 2 ** 30


def check_option(name: str, value: object) -> int:
    """``value`` (any integer type, numpy's too) as an ``int`` within ``BOUNDS[name]``; else
    :class:`BraveError` naming ``--name``."""
    if isinstance(value, Integral) and not isinstance(value, bool):
        value = int(value)
    BOUNDS[name].check(value, f"synth: --{name}")
    return value  # type: ignore[return-value]


def render_memory_bytes(width: int, height: int) -> int:
    """Estimated peak memory of one worker rendering ``width`` x ``height`` images (module docstring)."""
    return PROCESS_BYTES + BYTES_PER_PIXEL * width * height


def usable_cpus() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def available_memory_bytes() -> int | None:
    """Memory this process can still get: the kernel's ``MemAvailable``, lowered to what is left
    under this process's cgroup limit when there is one; None when unknown."""
    values = [v for v in (_meminfo_available(), _cgroup_headroom()) if v is not None]
    return min(values) if values else None


def _meminfo_available() -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def _cgroup_headroom() -> int | None:
    """``memory.max - memory.current`` of this process's cgroup (v2; v1's names), None without a limit."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        _, controllers, rel = (line.split(":", 2) + ["", ""])[:3]
        if controllers == "":
            folder, limit_name, usage_name = Path("/sys/fs/cgroup") / rel.lstrip("/"), "memory.max", "memory.current"
        elif "memory" in controllers.split(","):
            folder = Path("/sys/fs/cgroup/memory") / rel.lstrip("/")
            limit_name, usage_name = "memory.limit_in_bytes", "memory.usage_in_bytes"
        else:
            continue
        try:
            limit = (folder / limit_name).read_text().strip()
            usage = int((folder / usage_name).read_text().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < 2 ** 60:  # "max" or v1's huge number: no limit
            return max(int(limit) - usage, 0)
    return None


def check_machine(width: int, height: int, workers: int, processes: int, size_from: str) -> None:
    """Refuse, naming the flag, what this machine cannot run: a side over ``MAX_SIDE`` (``size_from``
    says where the size came from), more ``workers`` than ``OVERSUBSCRIPTION`` per CPU core (more than
    one per core is only warned about), or ``processes`` workers whose estimated memory exceeds what
    is available."""
    if width > MAX_SIDE or height > MAX_SIDE:
        raise BraveError(f"synth: {size_from} gives {width}x{height} images, more than {MAX_SIDE} pixels a side; "
                         f"give --width and --height (at most {MAX_SIDE})")
    cpus = usable_cpus()
    if workers > OVERSUBSCRIPTION * cpus:
        raise BraveError(f"synth: --workers {workers} is more than {OVERSUBSCRIPTION} x the {cpus} CPU core(s) this "
                         f"process may use; give --workers {cpus} (more than one per core only costs memory)")
    if workers > cpus:
        log.warning("synth: --workers %d on %d CPU core(s): workers beyond one per core share the cores and only "
                    "cost memory", workers, cpus)
    available = available_memory_bytes()
    each = render_memory_bytes(width, height)
    if available is not None and processes * each > available:
        raise BraveError(f"synth: {width}x{height} images (--width/--height) with --workers {workers} need about "
                         f"{processes * each / GIB:.1f} GiB ({processes} x {each / GIB:.1f} GiB: "
                         f"{PROCESS_BYTES / 2 ** 20:.0f} MiB + {BYTES_PER_PIXEL} B/pixel per worker), more than "
                         f"the {available / GIB:.1f} GiB available; use fewer --workers or smaller --width/--height")
