"""A few-view, downsampled crop of the real fox capture (instant-ngp format), built at test time.

``../shared/data/real/fox`` beside the checkout (50 photographs, 135x240, COLMAP poses) is not in
the repository; ``SP_FOX_CAPTURE`` points elsewhere (the same lookup as the benchmarks',
``bench.harness.scenes.FOX``). Tests that need it skip, naming the path, when it is missing; with
``CI=true`` (``.ci/run``) they fail instead, so a CI without the capture does not look green.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

from bench.harness.scenes import FOX  # one lookup for benches and tests: SP_FOX_CAPTURE, SP_SHARED_DATA, ../shared


def fox_missing(source: Optional[Path] = None) -> Optional[str]:
    """Why the capture cannot be used (a skip reason naming the path), or None when it can."""
    source = source or FOX
    where = "set SP_FOX_CAPTURE to a copy" if "SP_FOX_CAPTURE" not in os.environ else "SP_FOX_CAPTURE is set"
    if not (source / "transforms.json").is_file():
        return f"the fox capture is not here: no {source / 'transforms.json'} ({where})"
    try:
        frames = json.loads((source / "transforms.json").read_text())["frames"]
    except (ValueError, KeyError) as exc:
        return f"the fox capture at {source} has an unreadable transforms.json ({exc})"
    absent = [f["file_path"] for f in frames if not (source / f["file_path"]).is_file()]
    if absent or len(frames) < 2:
        return f"the fox capture at {source} is incomplete: {len(absent)} of {len(frames)} images missing ({where})"
    return None


def fox_available() -> bool:
    return fox_missing() is None


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
