"""LPIPS that never downloads (sp_plugins.adapter.lpips), exactly and without building the metric: where each
backbone's weights are looked for, which backbone a call asks for, what stands in without them, the one log
line per backbone, and the detached metric's device handling. A recording stand-in for the metric class
(the real one's construction is tested in tests/nerfstudio/test_ns_lpips.py). The mutants each test kills are listed in
``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import logging
import math
import os

import pytest
import torch
import torchvision.models as tvm

from sp_plugins.adapter import lpips


@pytest.fixture
def hub(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    monkeypatch.setattr(lpips, "_warned", set())
    return tmp_path


def cache(hub, net_type):
    url = {"alex": tvm.AlexNet_Weights, "vgg": tvm.VGG16_Weights, "squeeze": tvm.SqueezeNet1_1_Weights}[net_type].DEFAULT.url
    path = hub / "checkpoints" / url.rsplit("/", 1)[-1]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"weights")
    return path


@pytest.mark.parametrize("net_type", ["alex", "vgg", "squeeze"])
def test_each_backbone_is_looked_for_under_its_own_file_in_the_hub_cache(hub, net_type):
    """Each backbone's weights are looked for under its own file in the hub's ``checkpoints``; an unknown backbone
    has none."""
    assert not lpips.lpips_available(net_type)
    path = cache(hub, net_type)
    assert lpips.lpips_weights_path(net_type) == str(path) and lpips.lpips_available(net_type)
    assert lpips.lpips_weights_path("resnet") is None and not lpips.lpips_available("resnet")


def test_a_folder_in_place_of_the_weights_file_is_not_the_weights(hub):
    """A folder in place of the weights file does not count as the weights."""
    os.makedirs(lpips.lpips_weights_path("alex"))
    assert not lpips.lpips_available("alex")


class Metric(torch.nn.Module):
    """Records how it was built and called; ``device`` as torchmetrics' Metric tracks it."""

    def __init__(self, *args, **kwargs):
        super().__init__()
        self.args, self.kwargs, self.moved = args, kwargs, []
        self.device = torch.device("cpu")

    def to(self, device):
        self.moved.append(device)
        self.device = torch.device(device)
        return self

    def forward(self, a, b):
        return (a - b).abs().mean()


@pytest.mark.parametrize("args, kwargs, net_type", [((), {}, "alex"), (("vgg",), {}, "vgg"), ((), {"net_type": "squeeze"}, "squeeze"),
                                                    (("vgg",), {"net_type": "squeeze"}, "squeeze"), (("vgg", "mean"), {}, "vgg")])
def test_the_backbone_asked_for_decides_and_the_real_metric_gets_the_same_arguments(hub, args, kwargs, net_type):
    """``net_type`` from the keyword, else the first positional argument, else torchmetrics' default "alex"."""
    build = lpips.offline_factory(Metric)
    assert build.real is Metric
    assert isinstance(build(*args, **kwargs), lpips.MissingLPIPS)
    cache(hub, net_type)
    metric = build(*args, **kwargs)
    assert type(metric) is Metric and (metric.args, metric.kwargs) == (args, kwargs)
    detached = lpips.offline_factory(Metric, detach=True)(*args, **kwargs)
    assert type(detached) is lpips.DetachedMetric and type(detached.metric) is Metric and detached.available


def test_without_weights_the_stand_in_gives_nan_after_one_line_per_backbone(hub, caplog):
    """Without weights the stand-in metric gives NaN, after one warning line per backbone (not one per build)."""
    build = lpips.offline_factory(Metric)
    with caplog.at_level(logging.WARNING, logger=lpips.__name__):
        stand_ins = [build(), build(), build("vgg"), build(net_type="vgg")]
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and "the alex backbone" in lines[0] and "the vgg backbone" in lines[1]
    assert lpips.lpips_weights_path("alex") in lines[0]
    missing = stand_ins[0]
    assert not missing.available and missing.to("cpu") is missing
    assert math.isnan(float(missing(torch.rand(1, 3, 4, 4), torch.rand(1, 3, 4, 4))))


def test_the_detached_metric_moves_to_its_inputs_device_only_when_it_differs():
    """The detached metric moves to its inputs' device only when it differs, and keeps the moved metric; the model's
    ``.to()`` does not move it."""
    inner = Metric()
    metric = lpips.DetachedMetric(inner)
    a, b = torch.zeros(1, 3, 4, 4), torch.ones(1, 3, 4, 4)
    assert float(metric(a, b)) == 1.0 and inner.moved == []
    inner.device = torch.device("meta")  # as if it lived elsewhere
    assert float(metric(a, b)) == 1.0 and inner.moved == [torch.device("cpu")] and metric.metric is inner
    metric(a, b)
    assert inner.moved == [torch.device("cpu")]
    assert metric.to("cuda") is metric  # the host's model.to() does not move it
