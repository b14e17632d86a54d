"""Evaluation metrics: trajectory accuracy (ATE, RPE; per agent and for the team in one frame) and rendering
quality (PSNR, SSIM, depth L1). Definitions follow evo and the Gaussian-SLAM papers' evaluation code."""

from .align import ALIGN_MODES, PosePairs, Sim3, alignment, associate_poses, umeyama
from .ate import AteResult, ErrorStats, MultiAteResult, ate, ate_from_pairs, ate_multi
from .evaluate import TrajectoryEvaluation, evaluate_trajectories
from .image import depth_l1, psnr, ssim
from .rpe import RpeResult, rpe, rpe_from_pairs
from .team import TeamEvaluation, evaluate_team, find_team_trajectories

__all__ = [
    "ALIGN_MODES", "PosePairs", "Sim3", "alignment", "associate_poses", "umeyama",
    "AteResult", "ErrorStats", "MultiAteResult", "ate", "ate_from_pairs", "ate_multi",
    "RpeResult", "rpe", "rpe_from_pairs",
    "TrajectoryEvaluation", "evaluate_trajectories", "TeamEvaluation", "evaluate_team", "find_team_trajectories",
    "psnr", "ssim", "depth_l1",
]
