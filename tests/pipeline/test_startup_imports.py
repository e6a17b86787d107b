"""What a photo run imports: neither timm nor torchvision, which together cost ~5.5 s of start-up."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CHECK = """
import sys
from pathlib import Path
from physgm.model.checkpoint import input_size, load_model
from physgm.model.predict import predict_scene
from physgm.pipeline.prepared_input import prepare_input

model, ckpt = load_model("checkpoints/physgm_tiny.ckpt")
inp = prepare_input(Path("examples/jelly_cube.png"), input_size(model, ckpt.hparams))
predict_scene(model, inp.images, inp.masks, inp.c2w, inp.Ks, inp.classifier_images)
print(sorted(m for m in ("timm", "torchvision", "lightning", "lpips") if m in sys.modules))
"""


def test_predicting_a_photo_imports_no_timm_torchvision_or_lightning():
    done = subprocess.run(
        [sys.executable, "-c", CHECK], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "[]"
