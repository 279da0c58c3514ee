"""benchmarks/every_seed.py: each seed's row and the mean's wall-clock to 0.95, read from a run
folder's files."""

import importlib.util
import json
from pathlib import Path

import pytest

SPEC = importlib.util.spec_from_file_location(
    "every_seed", Path(__file__).parents[1] / "benchmarks" / "every_seed.py"
)
every_seed = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(every_seed)


def _folder(tmp_path: Path, name: str, curves: list[list[float]], chunk: int = 5) -> Path:
    """A run folder of len(curves[0]) seeds from base seed 100: success ``curves[u][s]`` at
    update u + 1, a wall-clock of 2 s per update, each seed's evaluation 0.9 + s / 100."""
    folder = tmp_path / name
    folder.mkdir()
    (folder / "run.json").write_text(json.dumps({"config": {"seed": 100}}))
    lines = ["seed,lam,budget,update,episode/success_rate"]
    for u, row in enumerate(curves):
        lines += [f"{s},0.0,,{u + 1},{v}" for s, v in enumerate(row)]
    (folder / "metrics.csv").write_text("\n".join(lines) + "\n")
    walls = [f"{u},{2.0 * u}" for u in range(chunk, len(curves) + 1, chunk)]
    (folder / "wall.csv").write_text("\n".join(["update,wall_s", *walls]) + "\n")
    runs = [
        {"seed": s, "episode/success_rate": 0.9 + s / 100, "episode/episode_length": 60.0 + s}
        for s in range(len(curves[0]))
    ]
    (folder / "results.json").write_text(json.dumps({"runs": runs}))
    return folder


def test_each_seed_its_pass_of_090_and_the_mean_its_wall_clock_to_095(tmp_path):
    # seed 0 is at 1.0 from update 1; seed 1 from update 11 (its 10-update average passes 0.9
    # at update 20, the mean's passes 0.95 at update 20 too); 30 updates
    curves = [[1.0, 0.0 if u < 10 else 1.0] for u in range(30)]
    out = tmp_path / "every_seed.json"
    folder = _folder(tmp_path, "a", curves)
    every_seed.main([str(folder), "--reference", str(folder), "--command", "c", "--out", str(out)])
    result = json.loads(out.read_text())
    assert result["command"] == "c"
    assert [s["seed"] for s in result["per_seed"]] == [100, 101]
    assert [s["update_090"] for s in result["per_seed"]] == [10, 20]
    assert [s["success"] for s in result["per_seed"]] == [0.9, 0.91]
    assert result["update_095"] == 20 and result["wall_s_to_095"] == 40.0
    assert result["reference"]["per_seed"] == result["per_seed"]


def test_a_seed_that_never_passes_has_no_update_and_a_mean_that_never_passes_no_time(tmp_path):
    curves = [[1.0, 0.5] for _ in range(20)]
    folder = _folder(tmp_path, "b", curves)
    result = every_seed.table(folder, 10)
    assert [s["update_090"] for s in result["per_seed"]] == [10, None]
    assert result["wall_s_to_095"] is None and result["update_095"] is None


def test_a_wall_clock_that_ends_before_the_update_is_refused(tmp_path):
    folder = _folder(tmp_path, "c", [[1.0] for _ in range(12)])
    with pytest.raises(ValueError, match="ends before update 13"):
        every_seed.wall_at(folder, 13)
