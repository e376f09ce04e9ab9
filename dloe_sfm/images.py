"""Image file names: the suffixes taken for images, natural name order, listing a folder.

Plain Python: the keypoint adapters use these without loading pycolmap.
"""

from __future__ import annotations

import re
from pathlib import Path

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", ".ppm", ".pgm")


def natural_key(name: str) -> tuple:
    """Sort key that orders embedded numbers numerically ('f9' < 'f10')."""
    return tuple(int(s) if s.isdigit() else s for s in re.split(r"(\d+)", name))


def list_images(image_dir: Path) -> list[str]:
    """Image files below ``image_dir`` as POSIX paths relative to it, in natural order."""
    names = [
        p.relative_to(image_dir).as_posix()
        for p in image_dir.rglob("*")
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    ]
    return sorted(names, key=natural_key)
