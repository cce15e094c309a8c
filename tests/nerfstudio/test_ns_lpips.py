"""LPIPS never downloads: stub + one log line when the backbone is not cached, the real metric when it is.

The cached case builds torchmetrics' real metric from a backbone file we write into a temporary
torch hub cache (random AlexNet weights: the metric's construction and loading are real, its values
are not LPIPS of a trained network)."""

from __future__ import annotations

import logging
import math
import os

import torch
import torchmetrics.image.lpip as lpip_module

from sp_plugins.adapter import lpips as shared
from sp_plugins.nerfstudio.components import lpips


def test_missing_weights_give_a_stub_and_one_log_line(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    monkeypatch.setattr(shared, "_warned", set())
    real = lpip_module.LearnedPerceptualImagePatchSimilarity
    with caplog.at_level(logging.WARNING, logger=shared.__name__):
        with lpips.offline_lpips():
            first = lpip_module.LearnedPerceptualImagePatchSimilarity(normalize=True)
            second = lpip_module.LearnedPerceptualImagePatchSimilarity()
    assert lpip_module.LearnedPerceptualImagePatchSimilarity is real  # restored
    assert isinstance(first, lpips.MissingLPIPS) and isinstance(second, lpips.MissingLPIPS)
    assert math.isnan(float(first(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8))))
    messages = [r.getMessage() for r in caplog.records if "LPIPS skipped" in r.getMessage()]
    assert len(messages) == 1 and str(tmp_path) in messages[0]


def test_cached_weights_build_the_real_metric_kept_out_of_the_state_dict(tmp_path, monkeypatch):
    import torchvision

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    path = lpips.lpips_weights_path("alex")
    os.makedirs(os.path.dirname(path))
    torch.save(torchvision.models.alexnet().state_dict(), path)
    real = lpip_module.LearnedPerceptualImagePatchSimilarity
    with lpips.offline_lpips():
        metric = lpip_module.LearnedPerceptualImagePatchSimilarity(normalize=True)
    assert type(metric) is real
    a, b = torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32)
    assert float(metric(a, a)) == 0.0 and float(metric(a, b)) > 0.0

    model = torch.nn.Module()
    model.lpips = metric
    assert any(k.startswith("lpips.") for k in model.state_dict())
    lpips.detach_lpips(model)
    assert not any(k.startswith("lpips.") for k in model.state_dict()) and model.lpips.metric is metric
    assert float(model.lpips(a, b)) == float(metric(a, b))
    assert lpips.drop_missing_lpips(model, {"psnr": 1.0, "lpips": 0.1}) == {"psnr": 1.0, "lpips": 0.1}
    model.lpips = lpips.MissingLPIPS()
    assert lpips.drop_missing_lpips(model, {"psnr": 1.0, "lpips": float("nan")}) == {"psnr": 1.0}
