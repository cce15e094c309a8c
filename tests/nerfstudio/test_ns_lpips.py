"""LPIPS never downloads: stub + one log line when the backbone is not cached, the real metric when it is."""

from __future__ import annotations

import logging
import math

import torch
import torchmetrics.image.lpip as lpip_module

from sp_plugins.nerfstudio import lpips


def test_missing_weights_give_a_stub_and_one_log_line(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    monkeypatch.setattr(lpips, "_warned", set())
    real = lpip_module.LearnedPerceptualImagePatchSimilarity
    with caplog.at_level(logging.WARNING, logger=lpips.__name__):
        with lpips.offline_lpips():
            first = lpip_module.LearnedPerceptualImagePatchSimilarity(normalize=True)
            second = lpip_module.LearnedPerceptualImagePatchSimilarity()
    assert lpip_module.LearnedPerceptualImagePatchSimilarity is real  # restored
    assert isinstance(first, lpips.MissingLPIPS) and isinstance(second, lpips.MissingLPIPS)
    assert math.isnan(float(first(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8))))
    messages = [r.getMessage() for r in caplog.records if "LPIPS skipped" in r.getMessage()]
    assert len(messages) == 1 and str(tmp_path) in messages[0]


def test_cached_weights_build_the_real_metric(tmp_path, monkeypatch):
    built = []

    class FakeMetric(torch.nn.Module):
        def __init__(self, *args, **kwargs):
            super().__init__()
            built.append(kwargs)
            self.weight = torch.nn.Parameter(torch.ones(1))

    monkeypatch.setattr(lpip_module, "LearnedPerceptualImagePatchSimilarity", FakeMetric)
    monkeypatch.setattr(lpips, "lpips_available", lambda net_type="alex": True)
    with lpips.offline_lpips():
        metric = lpip_module.LearnedPerceptualImagePatchSimilarity(normalize=True)
    assert isinstance(metric, FakeMetric) and built == [{"normalize": True}]

    # kept out of the model's state dict, still callable as model.lpips
    model = torch.nn.Module()
    model.lpips = metric
    assert "lpips.weight" in model.state_dict()
    lpips.detach_lpips(model)
    assert "lpips.weight" not in model.state_dict() and model.lpips.metric is metric
    metrics = lpips.drop_missing_lpips(model, {"psnr": 1.0, "lpips": 0.1})
    assert metrics == {"psnr": 1.0, "lpips": 0.1}
    model.lpips = lpips.MissingLPIPS()
    assert lpips.drop_missing_lpips(model, {"psnr": 1.0, "lpips": float("nan")}) == {"psnr": 1.0}
