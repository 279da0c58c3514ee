"""Results unchanged: three RL updates reproduce their recorded parameters.

On the machine the record was made on (same CPU model, usable cores, jax and jaxlib) the
parameters must be the recorded ones bit for bit. Elsewhere XLA's CPU kernels may round
differently (the thread count alone changes the last bits: 6.5e-7 relative on a leaf's sum
with one Eigen thread), so each parameter leaf's sum and norm must match to 1e-4: far above
rounding, far below what any change of the algorithm or its random stream does after three
Adam steps. After an intended change, re-record with
``python scripts/param_digest.py --record tests/data/rl3.json`` and say why in the commit.
"""

import importlib.util
import json
from pathlib import Path

import numpy as np

from sparsecomm.provenance import hardware

ROOT = Path(__file__).parent.parent
RECORD = json.loads((ROOT / "tests" / "data" / "rl3.json").read_text())
SAME_MACHINE = ("cpu", "usable_cores", "device_kind", "jax", "jaxlib")


def _param_digest():
    spec = importlib.util.spec_from_file_location("param_digest", ROOT / "scripts/param_digest.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_three_updates_reproduce_the_recorded_parameters():
    script = _param_digest()
    make, cfg, lam, budget = script.cases()[RECORD["case"]]
    got = script.summary(script.trained(make, cfg, lam, budget))
    np.testing.assert_allclose(got["sums"], RECORD["sums"], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(got["norms"], RECORD["norms"], rtol=1e-4)
    here = hardware()
    if all(here[k] == RECORD["machine"][k] for k in SAME_MACHINE):
        assert got["digest"] == RECORD["digest"]
