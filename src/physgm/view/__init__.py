"""The 4D viewer: simulated Gaussians over time in the browser (``python -m physgm.view RUN_DIR``).

``sequence`` holds the file a run folder keeps for it (``gaussians_t.npz``: the moving Gaussians,
written by simulate.py; ``motion`` the forms their motion is stored in); ``server`` serves it with
viser (``pip install physgm[view]``), imported only when the viewer starts.
"""

from physgm.view.sequence import SEQUENCE_FILE, GaussianSequence, sequence_file, sequence_from_trajectory

__all__ = ["SEQUENCE_FILE", "GaussianSequence", "sequence_file", "sequence_from_trajectory"]
