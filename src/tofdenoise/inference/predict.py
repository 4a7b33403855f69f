"""LightningCLI ``predict`` on a folder of camera frames, with no noise synthesis: ``FramesDataModule`` reads the
frames as ``tofdenoise denoise`` does and ``FramesPredictionWriter`` writes the same per-frame outputs::

    python -m tofdenoise.inference.predict predict --ckpt_path best.ckpt --data.inputs '[frames/]' \\
        --trainer.callbacks tofdenoise.inference.FramesPredictionWriter --trainer.callbacks.out_dir restored/

(``main``: a LightningCLI over ``DepthRestorer`` and ``FramesDataModule``; ``tofdenoise predict`` takes only
``ToFDataModule`` subclasses as ``--data``). LightningCLI reads the model's hyper-parameters from
``--ckpt_path``; the trainer defaults to no logger and the CPU/GPU Lightning picks. ``DepthRestorer.predict_step``
restores every frame (invalid input pixels back to 0; ``--fill-holes`` is the command's only), one frame per
batch.

Recordings among ``--data.inputs`` (Azure Kinect ``.mkv``, ROS bags; ``inference.recordings``) are read whole once
when the datamodule is built (a damaged one stops the run before any write) and their frames streamed after the
frame files, named ``<recording>/frame_NNNNNN`` as ``tofdenoise denoise`` names them; ``--data.depth_stream`` /
``--data.amplitude_stream`` choose their topics or tracks; a recording frame becomes a frame as in the command
(``RecordingFrame.frame``: the frame files' depth and amplitude checks), and the writer writes each recording's
``frames.csv`` (its frames and their timestamps) when the run ends. ``depth_scale_mm`` applies to frame files only:
other than 1 with a recording among the inputs it is refused (a recording's units are its encoding's). The writer's
``depth_m`` and ``ply`` options add the metres map and the point cloud (``ply`` takes those of ``intrinsics``, else a
recording's own, read only then).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import BasePredictionWriter
from torch.utils.data import DataLoader, Dataset, IterableDataset

from tofdenoise.inference.camera import Intrinsics, load_intrinsics, resolve_intrinsics
from tofdenoise.inference.frames import (
    AmplitudeSource,
    Frame,
    FrameInput,
    drop_amplitude_files,
    find_frames,
    load_frame,
)
from tofdenoise.inference.outputs import OutputOptions, frame_sigma, write_frame_outputs, write_recording_table
from tofdenoise.inference.recordings import Recording, RecordingError, find_recordings, open_recording

__all__ = ["FramesDataModule", "FramesDataset", "FramesPredictionWriter", "FramesStream", "main"]


def _item(frame: Frame, index: int, calib: Any, intrinsics: Intrinsics | None = None) -> dict[str, Any]:
    item: dict[str, Any] = {
        "noisy": torch.from_numpy(frame.depth_mm)[None],
        "mask": torch.from_numpy(frame.valid.astype(np.float32))[None],
        "index": index,
        "name": frame.name,
    }
    if frame.amplitude is not None:
        item["amplitude"] = torch.from_numpy(frame.amplitude)[None]
    sigma = frame_sigma(frame, calib)
    if sigma is not None:
        item["sigma"] = torch.from_numpy(sigma)[None]
    if intrinsics is not None:
        item["intrinsics"] = torch.tensor(
            [intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, intrinsics.width, intrinsics.height],
            dtype=torch.float64,
        )
    return item


class FramesDataset(Dataset):
    """One camera frame per item: ``noisy`` (1, H, W) depth mm (0 = invalid), ``mask``, optional ``amplitude``,
    ``sigma`` (sigma_D of the input, NaN = invalid; with a calibration and amplitude), ``name`` (output name)."""

    def __init__(
        self,
        frames: Sequence[FrameInput],
        depth_scale_mm: float = 1.0,
        amplitude: AmplitudeSource | None = None,
        calib: Any = None,
    ):
        self.frames = list(frames)
        self.depth_scale_mm = float(depth_scale_mm)
        self.amplitude = amplitude
        self.calib = calib

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> dict[str, Any]:
        frame = load_frame(self.frames[index], self.depth_scale_mm, self.amplitude)
        return _item(frame, index, self.calib)


class FramesStream(IterableDataset):
    """The frame files (``FramesDataset``), then every frame of each recording (``(RecordingInput, Recording)``
    pairs, opened and checked), as the same items; a recording frame carries its recording's ``intrinsics``."""

    def __init__(self, files: FramesDataset, recordings: Sequence[tuple[Any, Recording]], calib: Any = None):
        self.files = files
        self.recordings = list(recordings)
        self.calib = calib

    def __iter__(self):
        for index in range(len(self.files)):
            yield self.files[index]
        index = len(self.files)
        for source, recording in self.recordings:
            folder = source.rel_stem.as_posix()
            intrinsics, why = None, ""
            try:  # read here, used by the writer only for ply (an uncalibrated CameraInfo matters only then)
                intrinsics = recording.intrinsics
                why = "" if intrinsics is not None else f"recording {source.path}: {recording.intrinsics_absent()}"
            except RecordingError as exc:
                why = str(exc)
            for item in recording.frames():
                frame = item.frame(f"{folder}/frame_{item.index:06d}")
                out = _item(frame, index, self.calib, intrinsics)
                out.update(recording=folder, stamp_ns=item.stamp_ns, stream=recording.depth_name)
                out.update(frame_id=item.frame_id, intrinsics_absent=why)
                yield out
                index += 1


class FramesDataModule(L.LightningDataModule):
    """Predict-only datamodule over camera frames (no noise synthesis, no reference).

    Args:
        inputs: depth frames or folders of them (recursive), as ``tofdenoise denoise``.
        amplitude: amplitude frames paired by stem (folder, ``{stem}`` / ``{stem:OLD=NEW}`` template or glob);
            needed by checkpoints that use the signal channel.
        depth_scale_mm: millimetres per stored depth unit.
        sensor: the camera's calibration (file or preset) for the sigma_D map of the input (needs ``amplitude``;
            ``--data.sensor``, as ``data.sensor`` of the training configs and ``--sensor`` of the other verbs).
        exclude: folders whose files are not inputs (e.g. the output folder; an amplitude folder is excluded).
        num_workers: DataLoader workers.
        depth_stream: recordings: the depth topic / track (default: the Kinect's DEPTH track, the first image topic
            named like depth).
        amplitude_stream: recordings: the amplitude / IR topic / track (default: the Kinect's IR track, the first
            image topic named like ir / amplitude / intensity).
    """

    test_set_names = ["frames"]

    def __init__(
        self,
        inputs: list[str],
        amplitude: str | None = None,
        depth_scale_mm: float = 1.0,
        sensor: str | None = None,
        exclude: list[str] | None = None,
        num_workers: int = 0,
        depth_stream: str | None = None,
        amplitude_stream: str | None = None,
    ):
        super().__init__()
        self.save_hyperparameters()
        if not depth_scale_mm > 0:
            raise ValueError(f"FramesDataModule.depth_scale_mm must be > 0, got {depth_scale_mm}")
        if depth_scale_mm != 1 and find_recordings(inputs, exclude=exclude or []):
            raise ValueError(
                f"FramesDataModule.depth_scale_mm {depth_scale_mm:g} does not apply to recordings: a recording's "
                "depth units are its encoding's (16UC1 / mono16 and the Kinect's DEPTH track: mm; 32FC1: metres)"
            )
        if sensor is not None and amplitude is None:
            raise ValueError("FramesDataModule: sensor needs amplitude (the sigma_D map comes from the amplitude)")
        self.amplitude = AmplitudeSource(amplitude) if amplitude is not None else None
        skip = list(exclude or []) + ([self.amplitude.folder] if self.amplitude and self.amplitude.folder else [])
        self.frames = drop_amplitude_files(find_frames(inputs, exclude=skip), self.amplitude)
        self.recordings = []
        for source in find_recordings(inputs, exclude=skip):
            recording = open_recording(source.path, depth_stream, amplitude_stream)
            recording.scan()  # the whole recording is checked before anything is predicted or written
            self.recordings.append((source, recording))
        if not self.frames and not self.recordings:
            raise ValueError(f"FramesDataModule: no depth frame or recording found in {', '.join(map(str, inputs))}")
        self.calib = None
        if sensor is not None:
            from tofdenoise.physics.calibration import resolve_calibration

            self.calib = resolve_calibration(sensor)

    def predict_dataloader(self) -> DataLoader:
        dataset = FramesDataset(self.frames, self.hparams.depth_scale_mm, self.amplitude, self.calib)
        if self.recordings:  # streamed: a recording is read in order, not indexed
            stream = FramesStream(dataset, self.recordings, self.calib)
            return DataLoader(stream, batch_size=1, num_workers=0)
        return DataLoader(dataset, batch_size=1, shuffle=False, num_workers=int(self.hparams.num_workers))


class FramesPredictionWriter(BasePredictionWriter):
    """Writes each predicted frame as ``tofdenoise denoise`` does (``tofdenoise.inference.outputs``); ``depth_m``
    adds the metres TIFF, ``ply`` the point cloud (intrinsics: the frame's recording, else the ``intrinsics`` file)."""

    def __init__(
        self,
        out_dir: str,
        npy: bool = False,
        previews: bool = False,
        depth_m: bool = False,
        ply: bool = False,
        intrinsics: str | None = None,
    ) -> None:
        super().__init__(write_interval="batch")
        self.out_dir = Path(out_dir)
        self.options = OutputOptions(npy=npy, previews=previews, depth_m=depth_m, ply=ply)
        self.intrinsics = load_intrinsics(intrinsics) if intrinsics is not None else None
        self.written: list[Path] = []
        #: recording output folder -> (frame name, stamp_ns, stream, frame_id) of each frame written
        self.tables: dict[str, list[tuple[str, int, str, str]]] = {}

    def write_on_batch_end(
        self,
        trainer: Any,
        pl_module: Any,
        prediction: Any,
        batch_indices: Any,
        batch: Any,
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        pred = prediction["pred_mm"] if isinstance(prediction, dict) else prediction
        for i in range(pred.shape[0]):
            sigma = batch["sigma"][i, 0].cpu().numpy() if "sigma" in batch else None
            intrinsics = self.intrinsics
            if intrinsics is None and "intrinsics" in batch:
                fx, fy, cx, cy, w, h = (float(v) for v in batch["intrinsics"][i])
                intrinsics = Intrinsics(fx, fy, cx, cy, int(w), int(h), source="the recording")
            if intrinsics is not None and self.options.ply:
                intrinsics = resolve_intrinsics(intrinsics, tuple(pred.shape[-2:]), str(batch["name"][i]))
            elif self.options.ply and batch.get("intrinsics_absent", [""])[i]:
                raise ValueError(f"{batch['name'][i]}: {batch['intrinsics_absent'][i]}; ply needs intrinsics")
            self.written += write_frame_outputs(
                self.out_dir,
                str(batch["name"][i]),
                batch["noisy"][i, 0].cpu().numpy(),
                batch["mask"][i, 0].cpu().numpy() > 0,
                pred[i, 0].float().cpu().numpy(),
                self.options,
                sigma,
                intrinsics,
            )
            if "recording" in batch:
                row = (str(batch["name"][i]).rsplit("/", 1)[-1], int(batch["stamp_ns"][i]), str(batch["stream"][i]))
                self.tables.setdefault(str(batch["recording"][i]), []).append((*row, str(batch["frame_id"][i])))

    def on_predict_end(self, trainer: Any, pl_module: Any) -> None:
        """Each recording's ``frames.csv``: the frames written and their timestamps, as the command writes it."""
        for folder, rows in self.tables.items():
            self.written.append(write_recording_table(self.out_dir / folder, rows))


def main(args: list[str] | None = None) -> int:
    """``python -m tofdenoise.inference.predict predict --ckpt_path CKPT --data.inputs [...] ...``"""
    from lightning.pytorch.cli import LightningCLI

    from tofdenoise.training.module import DepthRestorer

    LightningCLI(
        DepthRestorer,
        FramesDataModule,
        args=args,
        save_config_callback=None,
        auto_configure_optimizers=False,
        trainer_defaults={"logger": False, "enable_checkpointing": False, "enable_model_summary": False},
    )
    return 0


if __name__ == "__main__":  # pragma: no cover
    main()
