"""PhysGM: feed-forward 4D synthesis from images with physical Gaussians.

Shape letters used in comments across the package:
    B batch, V input views, C cameras (render targets), N Gaussians, P particles,
    H W pixels, T frames, K samples, G grid nodes, M materials.
Units are SI everywhere (m, s, kg, Pa).
"""

__version__ = "0.1.0"
