import subprocess
import sys


def test_every_model_is_registered_by_importing_rflscm_models_alone():
    # A fresh interpreter: load_model() must find every model, without other imports;
    # the oracle is an evaluation device (rflscm.eval.oracle), not a model.
    code = "import rflscm.models as m; print(sorted(m.MODEL_REGISTRY))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['nerf2', 'rflscm', 'tiled', 'wnomp']"
