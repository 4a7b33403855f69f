"""best.ckpt is the epoch with the lowest val/mae_mm (scripted metric sequence); last.ckpt is the last one."""

from __future__ import annotations

from datetime import timedelta

import pytest
import torch

from tofdenoise.callbacks.checkpointing import BestAndLastCheckpoint
from tofdenoise.training.module import DepthRestorer

from .conftest import quiet_trainer

SCORES = [5.0, 3.0, 4.0, 2.0, 6.0, 2.0, 2.5]  # best at epoch 3 (the tie at epoch 5 does not replace it)


class ScriptedRestorer(DepthRestorer):
    """Logs a scripted val/mae_mm per epoch instead of the measured one."""

    scores: list[float] = SCORES

    def on_validation_epoch_end(self) -> None:
        self.val_metrics.reset()
        self.val_raw_metrics.reset()
        if self.trainer.sanity_checking:
            return
        self.log("val/mae_mm", self.scores[self.current_epoch])


@pytest.mark.parametrize(
    "refresh",
    [
        {},
        {"every_n_train_steps": 3},
        {"every_n_train_steps": 4},
        {"every_n_train_steps": 100},
        {"train_time_interval": timedelta(0)},
    ],
    ids=["per-validation", "step-mark-3", "step-mark-on-the-best-epoch", "step-mark-100", "every-step-by-time"],
)
def test_best_is_lowest_val_mae_and_last_is_last(tmp_path, tiny_data, refresh):
    """Whatever refreshes last.ckpt: with a step mark (3: at steps 3 and 6, between validations) Lightning's own
    trigger would have stored step 3's weights under epoch 1's score as "best", with a mark beyond the run
    (100: experiment=paper's 500 on a 450-step run) no best.ckpt at all. A refresh at the last step of an epoch (4:
    the best epoch's; a time interval that has always passed: every epoch's) must not keep that epoch's validation
    from choosing best.ckpt."""
    model = ScriptedRestorer(backbone="unet", backbone_kwargs={"width": 4, "stages": 2}, loss="l1")
    ckpt = BestAndLastCheckpoint(dirpath=tmp_path / "checkpoints", **refresh)
    trainer = quiet_trainer(
        tmp_path,
        max_epochs=len(SCORES),
        enable_checkpointing=True,
        callbacks=[ckpt],
        limit_train_batches=1,
        limit_val_batches=1,
    )
    trainer.fit(model, datamodule=tiny_data)
    files = sorted(p.name for p in (tmp_path / "checkpoints").iterdir())
    assert files == ["best.ckpt", "last.ckpt"]
    assert ckpt.best_model_path == str(tmp_path / "checkpoints" / "best.ckpt")
    assert float(ckpt.best_model_score) == pytest.approx(2.0)
    best = torch.load(tmp_path / "checkpoints" / "best.ckpt", weights_only=True)
    last = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)
    assert best["epoch"] == SCORES.index(min(SCORES)) == 3
    assert best["global_step"] == 4
    assert last["epoch"] == len(SCORES) - 1 and last["global_step"] == len(SCORES)
    # the weights in best.ckpt are those of the end of epoch 3, not the final ones
    final = model.state_dict()
    assert any(not torch.equal(best["state_dict"][k], final[k]) for k in final if k.startswith("backbone."))
    assert all(torch.equal(last["state_dict"][k], final[k]) for k in final)


def test_mode_and_step_mark_are_validated():
    with pytest.raises(ValueError, match="mode must be 'min' or 'max'"):
        BestAndLastCheckpoint(mode="lowest")
    with pytest.raises(ValueError, match="every_n_train_steps must be >= 0, got -1"):
        BestAndLastCheckpoint(every_n_train_steps=-1)


def test_a_checkpoint_write_that_fails_leaves_the_previous_one_intact_and_names_the_file(tmp_path):
    """A full disk mid-write: the partial file is removed, best.ckpt keeps its previous bytes, and the error names
    the checkpoint and the reason (Lightning's own path moved a temp file across file systems and left a
    truncated best.ckpt)."""
    import errno
    from types import SimpleNamespace

    from tofdenoise.callbacks.checkpointing import BestAndLastCheckpoint, CheckpointWriteError

    best = tmp_path / "best.ckpt"
    best.write_bytes(b"previous checkpoint")

    def full_disk(path, weights_only=False):
        with open(path, "wb") as fh:
            fh.write(b"half of a checkp")
        raise OSError(errno.ENOSPC, "No space left on device")

    def fine(path, weights_only=False):
        with open(path, "wb") as fh:
            fh.write(b"new checkpoint")

    cb = BestAndLastCheckpoint(dirpath=tmp_path)
    trainer = SimpleNamespace(save_checkpoint=full_disk, is_global_zero=True, global_step=7, loggers=[])
    with pytest.raises(CheckpointWriteError, match=r"could not write checkpoint .*best\.ckpt: No space left on device"):
        cb._save_checkpoint(trainer, str(best))
    assert best.read_bytes() == b"previous checkpoint"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["best.ckpt"]  # no temporary file left behind
    trainer.save_checkpoint = fine
    cb._save_checkpoint(trainer, str(best))
    assert best.read_bytes() == b"new checkpoint" and cb._last_checkpoint_saved == str(best)
    assert cb._last_global_step_saved == 7
