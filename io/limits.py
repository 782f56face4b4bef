"""What this machine can hold: the pixel budget of a panorama and the memory bound of the cube-face size.

Both come from one estimate, the features stage's peak memory, the largest per-pixel cost of a run that follows
the image's size (it decodes every panorama, at its native width with `features.working_width: 0`, and renders its
six cube faces with their remap maps, keep masks and one face's SIFT pyramid at a time). Measured with
`ru_maxrss` around decoding and `detect_features` on textured panoramas: 47-53 bytes per
panorama pixel at its native width (2048-6144 px wide), and 282-290 bytes per face_size² (faces of 1024-3072 px on a
1024 px panorama). The stage works on `FEATURES_IMAGES_AT_ONCE` images at a time, and a run may plan to use
`MEMORY_SHARE` of the machine's memory (the rest: the system, the viewer, the decoded images of other stages).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import PIL.Image

MEMORY_SHARE = 0.5  # of the machine's memory, what the features stage may plan to use
FEATURES_IMAGES_AT_ONCE = 2  # stages/features.py: two images at a time (threads=2)
FEATURES_BYTES_PER_PIXEL = 53  # peak of one image's features per panorama pixel at native width (measured 47-53)
FACE_BYTES_PER_SIDE2 = 290  # peak of one image's features per face_size² (six faces; measured 282-290)
_CGROUP_LIMIT = Path("/sys/fs/cgroup/memory.max")  # cgroup v2: a container's limit, lower than the machine's


def machine_memory() -> int:
    """Bytes of memory this process may use: the physical memory, or the cgroup's limit when that is lower."""
    physical = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    try:
        text = _CGROUP_LIMIT.read_text().strip()
    except OSError:
        return physical
    return min(physical, int(text)) if text.isdigit() else physical


def pixel_budget() -> int:
    """The most pixels a panorama may have: two of them at native width fit the features stage's share of memory.
    Capped at PIL's own decompression-bomb limit, above which PIL (EXIF, the viewer's tiles) refuses an image."""
    return int(min(_memory_pixels(), PIL.Image.MAX_IMAGE_PIXELS or math.inf))


def _memory_pixels() -> float:
    return MEMORY_SHARE * machine_memory() / (FEATURES_BYTES_PER_PIXEL * FEATURES_IMAGES_AT_ONCE)


def max_face_size() -> int:
    """The largest `features.face_size` whose faces, for two images at once, fit the features stage's share."""
    return int(math.sqrt(MEMORY_SHARE * machine_memory() / (FACE_BYTES_PER_SIDE2 * FEATURES_IMAGES_AT_ONCE)))


def memory_text() -> str:
    """Where the memory bounds come from, for messages."""
    return (f"{MEMORY_SHARE:g} of this machine's {machine_memory() / 2**30:.1f} GiB for the features of "
            f"{FEATURES_IMAGES_AT_ONCE} images at once")


def budget_text() -> str:
    """Where the pixel budget comes from, for messages."""
    if pixel_budget() < _memory_pixels():
        return f"PIL's decompression-bomb limit; {memory_text()} would allow {_memory_pixels() / 1e6:.0f} Mpx"
    return memory_text()
