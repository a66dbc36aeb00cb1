"""Mini-BEHAVIOR's household tasks as factored gymnasium environments (chapters 5.3 and 6.3).

Installing Printer (:mod:`.printer`), Thawing (:mod:`.thawing`) and Cleaning Car (:mod:`.cleaning_car`,
chapter 5's CarWash) re-implemented from the dissertation's text and the reference notes (Mini-BEHAVIOR
is not on PyPI; no code of the authors is used). 2D Minecraft (:mod:`envs.minecraft2d`) is built on
the same core: a grid room (:mod:`.grid`), action primitives on objects (:mod:`.primitives`),
dynamics as rules with exact local graphs (:mod:`.rules`) and the gymnasium environment
(:mod:`.core`); scripted and random policies are in :mod:`.scripted`.

Every factor is categorical; the action space is Discrete over (primitive, object) pairs; the
reward is +1 on success, which terminates the episode; ``info`` carries the true local graph and the
semantic stages reached (chapter 5's learning curves count them).
"""
from envs.household.cleaning_car import CleaningCarEnv
from envs.household.printer import InstallingPrinterEnv
from envs.household.thawing import ThawingEnv

__all__ = ["CleaningCarEnv", "InstallingPrinterEnv", "ThawingEnv"]
