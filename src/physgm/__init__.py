"""PhysGM: feed-forward 4D synthesis from images with physical Gaussians.

Shape letters used in comments across the package:
    B batch, V input views, C cameras (render targets), N Gaussians, P particles,
    H W pixels, T frames, K samples, G grid nodes, M materials.
Units are SI everywhere (m, s, kg, Pa).
"""

import os
import sys

__version__ = "0.1.0"
# Layout of training checkpoints (hyper_parameters + "model."-prefixed state dict); bump on any change
# that old code could misread. Written by the LightningModules, checked by physgm.pipeline.
CHECKPOINT_FORMAT_VERSION = 1


def _short_openmp_spin() -> None:
    """Lets torch's OpenMP workers sleep after 100k spins instead of 300k (GNU libgomp's default).

    physgm runs Warp CPU kernels on helper threads (``physgm.parallel``) between torch ops. After
    a parallel torch op, libgomp's idle worker spins on a core for its spin count before it
    sleeps: with the default, milliseconds, during which a helper thread woken for half a raster
    launch waits for that core, so the render's two-thread split runs no faster than one thread
    (docs/measurements.md, "Threads on a small CPU").
    libgomp reads the variable when it loads, so this works only if physgm is imported before
    torch: after that it is left unset, so that the environment still says what torch runs with
    (the render benchmark reports it). A value the user set is kept. Builds of torch on Intel's
    OpenMP read KMP_BLOCKTIME instead, which this does not touch.
    """
    if "GOMP_SPINCOUNT" not in os.environ and "torch" not in sys.modules:
        os.environ["GOMP_SPINCOUNT"] = "100000"


def _quiet_warp() -> None:
    # Warp logs its start-up banner and every module load at INFO; benchmarks print JSON on stdout.
    try:
        import warp
    except ImportError:  # pragma: no cover - warp is a hard dependency, but keep `import physgm` light
        return
    warp.config.log_level = warp.LOG_WARNING


_short_openmp_spin()
_quiet_warp()
