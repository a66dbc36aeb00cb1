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

Measured (``python -m benchmarks.bench_household``: 50,000 random-primitive steps per env; steps/s
per CPU second of one core, best of three, on this 2-core AMD EPYC machine shared with other jobs,
the range over three invocations; labels+: positive off-diagonal labels, action column included;
scripted policy over 50 unseen seeds):

============================  ====  ===  ==============  =======  ===============  ==============
environment                   d_S   |A|  steps/s/core    labels+  random success   scripted
============================  ====  ===  ==============  =======  ===============  ==============
installing-printer            12    5    50,000-53,000   4.9%     0.99             1.00, 6 steps
thawing thaw-fish             21    14   28,000-30,000   1.8%     0.49             1.00, 12 steps
thawing thaw-all              21    14   22,000-30,000   1.8%     0.14             1.00, 20 steps
cleaning-car clean-rag (100)  20    10   29,000-35,000   1.9%     0.00             1.00, 28 steps
cleaning-car clean-rag (300)  20    10   26,000-40,000   2.0%     0.14             1.00, 28 steps
minecraft2d diamond           24    15   22,000-24,000   0.7%     0.00             1.00, 28 steps
============================  ====  ===  ==============  =======  ===============  ==============

Chapter 5 reports at most 3% positive labels on Thawing and CarWash; these have 1.8-2.0%.
Installing Printer, with 12 factors, is denser. The random policy's mean fraction of stages
reached per episode: printer 1.00, thaw-fish 0.81, thaw-all 0.69, clean-rag 0.37 (100 steps) and
0.67 (300 steps), Minecraft 0.27.
"""
from envs.household.cleaning_car import CleaningCarEnv
from envs.household.printer import InstallingPrinterEnv
from envs.household.thawing import ThawingEnv

__all__ = ["CleaningCarEnv", "InstallingPrinterEnv", "ThawingEnv"]
