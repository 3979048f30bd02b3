"""benchmarks/speed.py: the speed suite's smoke test on the CPU (the torch backend; the GPU run is a benchmark)."""

import json

from benchmarks import speed
from benchmarks.tables import kind


def test_the_quick_suite_writes_one_record_per_variant_with_the_render_numbers_on_willags(tmp_path):
    out = tmp_path / "speed.json"
    assert speed.main(["--quick", "--variants", "willags-3dgs,willags", "--tag", "t", "--out", str(out)]) == 0
    recs = {r["method"]: r for r in json.loads(out.read_text())}
    assert sorted(recs) == ["willags", "willags-3dgs"]
    for r in recs.values():
        assert (r["scene"], r["steps"], r["tag"], r["device"]) == ("synthetic-box-3000-64px", 0, "t", "cpu")
        assert r["step_ms"] > 0 and r["n_gaussians"] == 3000 and kind(r) == "speed"  # merges as a speed record
    assert recs["willags"]["step_baseline"] == "willags-3dgs"  # no stock splatfacto without CUDA
    assert recs["willags-3dgs"]["step_ratio_vs_splatfacto"] == 1.0
    assert recs["willags"]["render_fps"] > 0 and recs["willags"]["render_fps_ratio_vs_gsplat"] > 0
    assert "render_fps" not in recs["willags-3dgs"]
