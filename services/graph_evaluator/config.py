"""graph-evaluator configuration."""
from __future__ import annotations

from dataclasses import dataclass

from proto.messages import BIASES, EDGE_RULES
from services.runtime.config import ServiceConfig, doc


@dataclass(frozen=True)
class GraphEvaluatorConfig(ServiceConfig):
    """graph-evaluator: the method's graph estimators on held-out transitions for every published weights version.

    The edge threshold is the method's own (in the model configuration the weights carry)."""

    edge_rule: str = doc("fixed", "how edges are decided: fixed (CMI >= the method's threshold, the chapter's "
                                  "0.02 nats) or fdr (each entry's test of CMI > min_cmi, from its standard "
                                  "error, at false-discovery rate fdr, Benjamini-Hochberg; needs a method whose "
                                  "graph has standard errors)", choices=EDGE_RULES)
    fdr: float = doc(0.05, "false-discovery rate of the fdr edge rule")
    min_cmi: float = doc(5e-3, "smallest CMI (nats) the fdr rule counts as an effect: a learned model's CMI of a "
                               "non-edge is biased slightly above 0 (docs/deviations.md)")
    bias: str = doc("fixed", "how the fdr rule allows for that bias: fixed (test CMI > min_cmi), permuted (test CMI > "
                             "the entry's CMI with its input permuted across the held-out samples, estimated in the "
                             "same pass; exact only for inputs independent of each other), pooled (test CMI > the "
                             "largest such null of the entry's output) or global (> the largest of the graph), "
                             "min_cmi then only marking undecided entries; or split (test CMI > a minimum effect "
                             "size cut from each estimate's CMI table, the gap between its two clusters of log CMI, "
                             "min_cmi where it has none; needs no null) or mirror (edge if CMI >= the smallest level "
                             "where the entries below minus it, the non-edges' mirror image, are at most fdr of "
                             "those above it; for a model whose non-edges are as often below 0 as above; needs no "
                             "null) or mirror-permuted (the same levels of CMI minus the permuted null and of its "
                             "z-score; edge if above both; for models whose non-edges' CMI is biased either way) "
                             "(causal.edge_tests)", choices=BIASES)

    heldout_capacity: int = doc(40_000, "held-out transitions kept (a ring buffer): each evaluation draws "
                                "eval_samples of them, so successive estimates see different episodes")
    min_heldout: int = doc(500, "held-out transitions needed before the first report")
    eval_samples: int = doc(2_000, "held-out transitions used per evaluation (the first draw; see eval_samples_max)")
    eval_samples_max: int = doc(16_000, "most held-out transitions per evaluation: when the graph has stayed the same "
                                        "for eval_growth_reports reports with some entry still undecided, the draw "
                                        "doubles, up to this (more data where it decides; at most eval_samples: never "
                                        "grows); only for a method whose graph has standard errors")
    eval_growth_reports: int = doc(3, "reports in a row with the same graph and an undecided entry before the "
                                      "evaluation draw doubles")
    cmi_ema: float = doc(0.999, "weight of the previous edge-score estimate per learner update since it "
                         "(the reference's EMA): an evaluation k updates later keeps cmi_ema**k of it")
    min_interval_s: float = doc(2.0, "minimum seconds between evaluations")
    local_capacity: int = doc(10_000, "held-out transitions kept with their true local graphs (for methods with a "
                                      "local-graph estimator, on envs whose workers send local graphs)")
    local_samples: int = doc(1_000, "held-out transitions whose local graphs are scored per evaluation")
    local_examples: int = doc(4, "example transitions each local-graph report carries for display")
    induced_graphs: bool = doc(False, "publish the local graphs the method's estimator induces for every step of every "
                                      "batch (InducedGraphs on induced/<method>/<worker>): SkiLD's induced graphs")

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0.0 <= self.cmi_ema < 1.0:
            raise ValueError(f"cmi_ema must be in [0, 1), got {self.cmi_ema}")
        if self.eval_samples <= 0 or self.min_heldout < 1 or self.heldout_capacity < self.min_heldout:
            raise ValueError("eval_samples and min_heldout must be positive and heldout_capacity >= min_heldout")
        if self.eval_samples_max < 0 or self.eval_growth_reports < 1:
            raise ValueError(f"eval_samples_max must be >= 0 and eval_growth_reports >= 1, got "
                             f"{self.eval_samples_max}, {self.eval_growth_reports}")
        if not 0.0 < self.fdr < 1.0 or not 0.0 <= self.min_cmi < float("inf"):
            raise ValueError(f"fdr must be in (0, 1) and min_cmi finite and >= 0, got {self.fdr}, {self.min_cmi}")
        if self.local_capacity < 1 or self.local_samples < 1 or not 0 <= self.local_examples <= 64:
            raise ValueError("local_capacity and local_samples must be >= 1, local_examples in [0, 64]")
