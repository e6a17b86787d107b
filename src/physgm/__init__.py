"""PhysGM: feed-forward 4D synthesis from images with physical Gaussians.

Shape letters used in comments across the package:
    B batch, V input views, C cameras (render targets), N Gaussians, P particles,
    H W pixels, T frames, K samples, G grid nodes, M materials.
Units are SI everywhere (m, s, kg, Pa).
"""

__version__ = "0.1.0"
# Layout of training checkpoints (hyper_parameters + "model."-prefixed state dict); bump on any change
# that old code could misread. Written by the LightningModules, checked by physgm.pipeline.
CHECKPOINT_FORMAT_VERSION = 1


def _quiet_warp() -> None:
    # Warp logs its start-up banner and every module load at INFO; benchmarks print JSON on stdout.
    try:
        import warp
    except ImportError:  # pragma: no cover - warp is a hard dependency, but keep `import physgm` light
        return
    warp.config.log_level = warp.LOG_WARNING


_quiet_warp()
