"""H.264 mp4 files: the one encoding every physgm video is written with, and reading one back.

The pipeline's videos, the data generator's reference drop videos and the DPO scorer's codec
round trip (``physgm.data.video.codec_round_trip``) all go through ``write_mp4``. The round trip
exists to give a rollout the same codec artefacts as the reference video it is scored against,
so the references and the round trip must share the encoder settings exactly: one function
keeps them from drifting apart.

Settings: libx264, yuv420p, constant quality CRF 18, x264's default preset ("medium"; the
reference videos on disk were encoded with it, and a faster preset changes the artefacts the
round trip reproduces), one encoder thread and the bit-exact flags without metadata, so the same
frames give the same bytes on every machine.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

CRF = 18  # x264 constant quality: visually lossless for these renders


def write_mp4(path: Path | str, frames: np.ndarray, fps: float) -> None:
    """Write uint8 frames [T, H, W, 3] (H and W even: yuv420p) as an H.264 mp4 at ``fps``."""
    import imageio_ffmpeg

    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"frames must be uint8 [T, H, W, 3], got {frames.dtype} {tuple(frames.shape)}")
    h, w = frames.shape[1:3]
    writer = imageio_ffmpeg.write_frames(
        str(path),
        (w, h),
        fps=fps,
        codec="libx264",
        pix_fmt_out="yuv420p",
        quality=None,
        macro_block_size=1,
        output_params=[
            "-crf",
            str(CRF),
            "-threads",
            "1",
            "-fflags",
            "+bitexact",
            "-flags:v",
            "+bitexact",
            "-map_metadata",
            "-1",
        ],
        ffmpeg_log_level="error",
    )
    writer.send(None)
    for f in frames:
        writer.send(np.ascontiguousarray(f))
    writer.close()


def read_mp4(path: Path | str, n_frames: int | None = None) -> np.ndarray:
    """Frames [T, H, W, 3] uint8 of an mp4, the first ``n_frames`` only when given."""
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    w, h = next(reader)["size"]
    frames = []
    for buf in reader:
        frames.append(np.frombuffer(buf, np.uint8).reshape(h, w, 3))
        if n_frames is not None and len(frames) >= n_frames:
            break
    reader.close()
    return np.stack(frames)
