"""Data: the PhysAssets on-disk format, synthetic assets, mesh import and the datamodule.

Modules (see docs/data.md):
    format       folder layout, ``load_asset``/``read_asset``, ``Asset``, split lists
    check        ``python -m physgm.data.check ROOT``: every defect in one pass
    synth        ``python -m physgm.data.synth``: procedural Gaussian assets (+ drop videos, video.py)
    shapes, appearance, procedural, priors, annotation   the pieces of a synthetic asset
    from_meshes  ``python -m physgm.data.from_meshes``: textured meshes by CPU ray casting (raycast.py)
    real_objects ``python -m physgm.data.real_objects``: the hand-labelled real-object val/test set (mjcf.py)
    views, datamodule   example cutting and ``PhysAssetsDataModule`` -> ``Batch``
    shards       ``python -m physgm.data.shards``: litdata shards for multi-node streaming
"""

from physgm.data.format import Asset, AssetError, PhysicalLabels, load_asset, read_asset, read_split

__all__ = ["Asset", "AssetError", "PhysicalLabels", "load_asset", "read_asset", "read_split"]
