"""A few-view, downsampled crop of the real fox capture (instant-ngp format), built at test time.

``/work/shared/data/real/fox`` (50 photographs, 135x240, COLMAP poses) is not in the repository;
``SP_FOX_CAPTURE`` points elsewhere. Tests that need it skip when it is missing.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

FOX = Path(os.environ.get("SP_FOX_CAPTURE", "/work/shared/data/real/fox"))


def fox_available() -> bool:
    return (FOX / "transforms.json").is_file()


def make_fox_crop(out: Path, views: int = 6, factor: int = 5, source: Optional[Path] = None) -> Path:
    """``views`` evenly spaced frames, each image shrunk ``factor`` times (intrinsics scaled to
    match; the distortion coefficients are in normalised coordinates and stay)."""
    from PIL import Image

    source = source or FOX
    meta = json.loads((source / "transforms.json").read_text())
    frames = meta["frames"]
    picked = [frames[round(i * (len(frames) - 1) / (views - 1))] for i in range(views)]
    w, h = int(meta["w"]) // factor, int(meta["h"]) // factor
    sx, sy = w / meta["w"], h / meta["h"]
    (out / "images").mkdir(parents=True, exist_ok=True)
    for frame in picked:
        with Image.open(source / frame["file_path"]) as im:
            im.convert("RGB").resize((w, h), Image.LANCZOS).save(out / frame["file_path"])
    crop = {k: v for k, v in meta.items() if k not in ("frames", "camera_angle_x", "camera_angle_y")}
    crop.update(w=w, h=h, fl_x=meta["fl_x"] * sx, fl_y=meta["fl_y"] * sy, cx=meta["cx"] * sx, cy=meta["cy"] * sy)
    crop["frames"] = [{"file_path": f["file_path"], "transform_matrix": f["transform_matrix"]} for f in picked]
    (out / "transforms.json").write_text(json.dumps(crop, indent=1))
    return out
