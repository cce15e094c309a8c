"""``sp-sweep`` of a tiny nerfstudio method as a user runs it: ``ns-train`` then ``ns-eval`` per
trial on a local Ray with 2 CPUs, the grid value and the SP axis reaching the trainer's config."""

from __future__ import annotations

import pytest

NS_TINY = ("--max-num-iterations 2 --steps-per-save 2 --logging.local-writer.enable False "
           "--pipeline.datamanager.train-num-rays-per-batch 32 --pipeline.datamanager.eval-num-rays-per-batch 256 "
           "--pipeline.model.num-samples 8 --pipeline.model.num-samples-importance 8 "
           "--pipeline.model.num-up-sample-steps 1 --pipeline.model.background-model none "
           "--pipeline.model.eval-num-rays-per-chunk 512 --pipeline.model.sdf-field.hidden-dim 16 "
           "--pipeline.model.sdf-field.hidden-dim-color 16 --pipeline.model.sdf-field.geo-feat-dim 7 "
           "--pipeline.model.sdf-field.num-levels 4 --pipeline.model.sdf-field.log2-hashmap-size 10")
PSNR_RULE = "psnr >= 5"


@pytest.mark.timeout(1800)
def test_ns_train_sweep_of_a_tiny_method(run_sweep, rows, sweep_scene, tmp_path):
    out = tmp_path / "ns"
    # one grid point, off-default (the host's max_res is 2048), paired: baseline and SP
    spec = {"command": f"ns-train neus-hashgrid {NS_TINY}", "data": f"blender-data --data {sweep_scene / 'blender'}",
            "grid": {"pipeline.model.sdf-field.max-res": [48]}, "success": [PSNR_RULE]}
    run_sweep(spec, out)
    table = rows(out)
    assert len(table) == 2 and sorted(r["sp"] for r in table) == ["SP", "baseline"], table
    for r in table:
        assert r["status"] == "ok", r["error"]
        assert 0 < float(r["psnr"]) < 60 and 0 < float(r["ssim"]) <= 1
        assert float(r["success"]) == 1 and float(r["psnr"]) >= 6, r  # the rule holds, with a margin
        (config,) = (out / "trials" / r["trial"]).glob("train/**/config.yml")
        text = config.read_text()
        assert "max_res: 48" in text and r["max-res"] == "48"  # the grid value reached the trainer
        sp_on = r["sp"] == "SP"
        assert ("enabled: true" in text) == sp_on  # the SP axis reached the trainer
    assert f"success ({PSNR_RULE}): baseline 1/1 (100%), SP 1/1 (100%)" in (out / "results.md").read_text()
