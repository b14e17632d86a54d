"""What a run keeps on disk as it goes (progress/ in its output folder): the pose journal (journal.PoseJournal)."""

from .journal import PoseJournal

__all__ = ["PoseJournal"]
