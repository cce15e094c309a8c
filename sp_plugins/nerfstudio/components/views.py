"""Train on only N of the training views (the sparse-view setting, e.g. FreeNeRF's).

nerfstudio has no fixed view subset: ``train_num_images_to_sample_from`` re-draws its subset
periodically and the nerfstudio dataparser's ``train_split_fraction`` is a fraction of a layout
without split files. :func:`select_views` keeps N views of the training split's
``DataparserOutputs``; the checked data managers of sp-plugins apply it when
``--pipeline.datamanager.train-views N`` is given, so it works for every method here and for any
dataparser. Held-out (eval/test) views are untouched.
"""

from __future__ import annotations

import dataclasses
from typing import List, Literal, Sequence

import torch
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs

ViewSelection = Literal["spread", "first", "random"]
VIEW_SELECTIONS = ("spread", "first", "random")

PER_IMAGE_TENSOR_KEYS = ("camera_to_worlds",)
"""Metadata tensors indexed by image (SDFStudio's). Lists as long as the image list (depth, normal
and other filename lists) are subset too; everything else is passed through."""


def farthest_views(centres: torch.Tensor, n: int) -> List[int]:
    """Greedy farthest-point order of camera centres ``[M, 3]``, starting from view 0: each next
    view is the one farthest from those already chosen (deterministic, covers the orbit)."""
    chosen = [0]
    dist = torch.linalg.norm(centres - centres[0], dim=-1)
    for _ in range(n - 1):
        i = int(torch.argmax(dist))
        chosen.append(i)
        dist = torch.minimum(dist, torch.linalg.norm(centres - centres[i], dim=-1))
    return chosen


def view_indices(outputs: DataparserOutputs, n: int, selection: ViewSelection = "spread", seed: int = 0) -> List[int]:
    """Which ``n`` of the views in ``outputs`` to keep, sorted."""
    total = len(outputs.image_filenames)
    if n < 1:
        raise ValueError(f"train_views={n}: give a number of views >= 1 (or -1 for all)")
    if n > total:
        raise ValueError(f"train_views={n}: the training split has only {total} views; give at most {total} (or -1 for all)")
    if selection == "first":
        chosen = list(range(n))
    elif selection == "random":
        g = torch.Generator().manual_seed(seed)
        chosen = torch.randperm(total, generator=g)[:n].tolist()
    elif selection == "spread":
        chosen = farthest_views(outputs.cameras.camera_to_worlds[:, :3, 3].float(), n)
    else:
        raise ValueError(f"train_view_selection={selection!r}: allowed values are {', '.join(VIEW_SELECTIONS)}")
    return sorted(chosen)


def subset_views(outputs: DataparserOutputs, indices: Sequence[int]) -> DataparserOutputs:
    """``outputs`` restricted to the views ``indices`` (images, cameras, masks, per-image metadata)."""
    total = len(outputs.image_filenames)
    idx = list(indices)
    if not idx or min(idx) < 0 or max(idx) >= total or len(set(idx)) != len(idx):
        raise ValueError(f"view indices {idx}: need distinct indices in [0, {total - 1}]")

    def pick(values):
        return [values[i] for i in idx]

    metadata = {}
    for key, value in outputs.metadata.items():
        if isinstance(value, (list, tuple)) and len(value) == total:
            value = pick(value)
        elif key in PER_IMAGE_TENSOR_KEYS and isinstance(value, torch.Tensor) and value.shape[0] == total:
            value = value[idx]
        metadata[key] = value
    return dataclasses.replace(
        outputs,
        image_filenames=pick(outputs.image_filenames),
        cameras=outputs.cameras[torch.tensor(idx)],
        mask_filenames=None if outputs.mask_filenames is None else pick(outputs.mask_filenames),
        metadata=metadata,
    )


def select_views(outputs: DataparserOutputs, n: int, selection: ViewSelection = "spread", seed: int = 0) -> DataparserOutputs:
    """Keep ``n`` views of ``outputs`` (all of them when ``n`` is -1)."""
    if n == -1:
        return outputs
    return subset_views(outputs, view_indices(outputs, n, selection, seed))
