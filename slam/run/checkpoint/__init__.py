"""What a run keeps on disk as it goes (progress/ in its output folder): the pose journal (journal.PoseJournal,
every run) and the checkpoints `--resume` continues from (state; a single-agent run or an in-process team)."""

from .journal import PoseJournal
from .state import CHECKPOINT, Resumed, find_resume, has_checkpoint, load_checkpoint, run_identity, save_checkpoint, \
    team_identity

__all__ = ["CHECKPOINT", "PoseJournal", "Resumed", "find_resume", "has_checkpoint", "load_checkpoint", "run_identity",
           "save_checkpoint", "team_identity"]
