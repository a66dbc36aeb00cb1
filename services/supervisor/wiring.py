"""The wiring of a local run, readable in one place: what is checked before anything starts, which
services run, and what each one is told.

Everything a run takes is checked by :func:`resolve` before a process starts (``ValueError`` with the
reason and, for names, the valid ones): the environment's options (a graph file is parsed), the task
against the environment, the intrinsic reward against the method, the collector against the action
space, a target metric against what the method and the environment can score.
"""
from __future__ import annotations

import dataclasses
import socket
import time
from pathlib import Path
from typing import Any

from causal.intrinsic import make_reward
from causal.method import Method, has_standard_errors, permuted_null_refusal
from causal.factored import FactorLayout
from causal.methods import get_method, method_config
from envs.registry import EnvEntry, check_options, env_entry, make_env
from proto.messages import NULL_BIASES, EnvSpec
from services.bus.credentials import RouterAuth, role_file, write_run_secrets
from services.bus.roles import access_control, instance_user, new_passwords, run_roles
from services.bus.router import free_tcp_port
from services.dashboard.config import DashboardConfig
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.frames import has_frames
from services.runtime.config import RunSettings
from services.supervisor.config import RunConfig

LOOPBACK = "127.0.0.1"
"""Where the local stack's services listen (/metrics, the page): nothing of a local run is reachable
from another machine."""

MODULES = {"env-worker": "services.env_worker", "dynamics-learner": "services.dynamics_learner",
           "graph-evaluator": "services.graph_evaluator", "dashboard": "services.dashboard",
           "policy-learner": "services.policy_learner", "intrinsic-reward": "services.intrinsic_reward",
           "factor-extractor": "services.factor_extractor"}
"""Service name -> the module its process runs (``python -m <module>``)."""


def resolve(cfg: RunConfig) -> RunConfig:
    """``cfg`` checked, with the derived defaults filled in: the task's environment, run id, run
    directory, router port. ``ValueError`` names what is wrong and what would be right."""
    entry = _entry(cfg.env)
    try:
        method = get_method(cfg.method)
    except KeyError as exc:
        raise ValueError(exc.args[0]) from None
    task = cfg.env_options.task
    if task:
        if task not in entry.tasks:
            raise ValueError(f"environment {cfg.env!r} poses no task {task!r}; its tasks: "
                             f"{', '.join(entry.tasks) or 'none'}")
        cfg = dataclasses.replace(cfg, env=entry.tasks[task])
        entry = _entry(cfg.env)
    check_options(cfg.env, cfg.env_options)
    if method.envs and cfg.env not in method.envs:
        raise ValueError(f"method {cfg.method!r} runs on {', '.join(method.envs)} only, not {cfg.env!r}")
    if cfg.env in method.env_settings:
        implied = dataclasses.replace(method_config(cfg.models, cfg.method), **method.env_settings[cfg.env])
        cfg = dataclasses.replace(cfg, models=dataclasses.replace(cfg.models, **{cfg.method: implied}))
    if method.check_layout is not None:
        method.check_layout(FactorLayout.from_spec(run_env_spec(cfg)), method_config(cfg.models, cfg.method))
    _check_policy(cfg, method.intrinsic)
    _check_skill_discovery(cfg, entry)
    if cfg.target_f1 and method.global_graph is None:
        raise ValueError(f"method {cfg.method!r} estimates no global graph: --target-f1 has nothing to reach")
    _check_edge_tests(cfg, method)
    _check_frames(cfg, method)
    _check_latent_labels(cfg, method)
    if cfg.target_f1 and not entry.has_global_truth:
        raise ValueError(f"environment {cfg.env!r} has no true global graph to score --target-metric against")
    run_id = cfg.run_id or (Path(cfg.run_dir).name if cfg.run_dir else
                            f"{cfg.env}-{Path(cfg.env_options.graph).stem if 'graph' in entry.options else cfg.method}"
                            f"-s{cfg.seed}-{time.strftime('%Y%m%d-%H%M%S')}")
    run_id = "".join(c if c.isalnum() or c in "_.-" else "-" for c in run_id)
    return dataclasses.replace(cfg, run_id=run_id, run_dir=cfg.run_dir or f"runs/{run_id}",
                               router_port=cfg.router_port or free_tcp_port())


def _entry(name: str) -> EnvEntry:
    try:
        return env_entry(name)
    except KeyError as exc:
        raise ValueError(exc.args[0]) from None


def _check_latent_labels(cfg: RunConfig, method: Method) -> None:
    """``--label-latent-actions`` needs a method with latent actions (FLAM) and full-size frames."""
    if not cfg.label_latent_actions:
        return
    if method.latent_actions is None:
        raise ValueError(f"--label-latent-actions: method {cfg.method!r} has no latent actions (flam has)")
    if cfg.worker.publish_frames:
        raise ValueError("--label-latent-actions publishes frames beside the transitions; leave "
                         "--worker-publish-frames false")
    if cfg.worker.frame_stride != 1:
        raise ValueError(f"--label-latent-actions: the FLAM model reads whole frames; --worker-frame-stride must be 1, "
                         f"got {cfg.worker.frame_stride}")


def _check_frames(cfg: RunConfig, method: Method) -> None:
    """``--worker-publish-frames`` needs an env that renders frames (``info["frame"]``) with its masks when
    the extractor's mask prior uses them, and a method that learns over factors: a pixel method (Dyn-O,
    FLAM) draws its own frames from the states, which a slot stream no longer carries."""
    if not cfg.worker.publish_frames:
        return
    if method.slots is not None or method.latent_actions is not None:
        raise ValueError(f"--worker-publish-frames: method {cfg.method!r} learns from frames itself; the "
                         f"factor-extractor's slot transitions are for a method over factors (cdl, cbm, elden, ...)")
    info = make_env(cfg.env, **env_kwargs(cfg)).reset(seed=cfg.seed)[1]
    if not has_frames(info):
        raise ValueError(f"--worker-publish-frames: {cfg.env} renders no frames (chemical-pixels does)")
    if cfg.extractor.slot.mask_prior != "none" and "masks" not in info:
        raise ValueError(f"--extractor-slot-mask-prior {cfg.extractor.slot.mask_prior} needs the frames' masks; "
                         f"{cfg.env} gives none (use none)")
    if cfg.extractor.identity == "learned":
        if "masks" not in info:
            raise ValueError(f"--extractor-identity learned fits its head on the frames' masks; {cfg.env} gives none "
                             f"(use --extractor-identity none)")
        segments = len(info["masks"])
        if cfg.extractor.num_slots not in (0, segments):
            raise ValueError(f"--extractor-identity learned names one slot per segment: --extractor-num-slots must be "
                             f"0 or {segments} on {cfg.env}, got {cfg.extractor.num_slots} (or --extractor-identity none)")


def _check_edge_tests(cfg: RunConfig, method: Method) -> None:
    """The FDR edge rule and the stability stop rule need a global graph with standard errors."""
    stable = cfg.stable_reports or cfg.stable_seconds
    if (cfg.evaluator.edge_rule == "fdr" or stable) and not has_standard_errors(method):
        what = "--evaluator-edge-rule fdr" if cfg.evaluator.edge_rule == "fdr" else "--stable-reports/--stable-seconds"
        raise ValueError(f"{what} needs a global graph with standard errors (to test edges, to know none is "
                         f"undecided); method {cfg.method!r} has none")
    if cfg.evaluator.bias in NULL_BIASES:
        refusal = permuted_null_refusal(method, getattr(cfg.models, method.name, None))
        if refusal:
            raise ValueError(f"--evaluator-bias {cfg.evaluator.bias}: {refusal}")
    elif cfg.evaluator.bias != "fixed" and not has_standard_errors(method):
        raise ValueError(f"--evaluator-bias {cfg.evaluator.bias} needs a global graph with standard errors; "
                         f"method {cfg.method!r} has none")


def skill_discovery(cfg: RunConfig) -> bool:
    """Whether the run is SkiLD's (ch. 6): its policy-learner learns skills then a task policy over
    them, the env-workers act with those policies and the evaluator sends the induced graphs."""
    return cfg.method == "skild"


def _check_skill_discovery(cfg: RunConfig, entry: EnvEntry) -> None:
    if not skill_discovery(cfg):
        return
    if cfg.collector != "random" or cfg.intrinsic != "none":
        raise ValueError("SkiLD collects with its own skill and task policies: leave --collector random and "
                         "--intrinsic none")
    spec = run_env_spec(cfg)
    if spec.action_kind != "categorical" or any(k != "categorical" for k in spec.factor_kinds):
        raise ValueError(f"SkiLD learns over categorical factors and actions; {cfg.env} has others")
    if cfg.policy.skild_graphs == "true" and not entry.has_local_truth:
        raise ValueError(f"--policy-skild-graphs true needs the env's true local graphs; {cfg.env} has none")
    if cfg.max_env_steps and cfg.max_env_steps <= cfg.policy.skild_pretrain_steps:
        raise ValueError(f"--max-env-steps {cfg.max_env_steps} leaves no task learning after "
                         f"--policy-skild-pretrain-steps {cfg.policy.skild_pretrain_steps}")


def _check_policy(cfg: RunConfig, served: tuple[str, ...]) -> None:
    if cfg.intrinsic != "none":
        if cfg.collector == "random":
            raise ValueError("an intrinsic reward needs a policy to train: use --collector ppo or sac")
        if make_reward(cfg.intrinsic).source == "dynamics" and cfg.intrinsic not in served:
            raise ValueError(f"--intrinsic {cfg.intrinsic} reads the dynamics model, and method {cfg.method!r} "
                             f"serves {', '.join(served) or 'no such reward'}")
    if cfg.collector == "sac" and run_env_spec(cfg).action_kind == "categorical":
        raise ValueError(f"SAC needs continuous actions; {cfg.env} has discrete ones (use --collector ppo)")


def shared_settings(cfg: RunConfig) -> dict[str, Any]:
    """The run-wide settings every service gets (:class:`RunSettings`)."""
    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(RunSettings)}


def service_configs(cfg: RunConfig, connect: str, worker_index: int = 0) -> dict[str, object]:
    """The wiring: what each service is told (all of it lands in <run_dir>/config.json)."""
    common = dict(shared_settings(cfg), run_id=cfg.run_id, zenoh_connect=connect, run_dir=cfg.run_dir,
                  metrics_host=LOOPBACK)

    def port(offset: int) -> int:
        return cfg.metrics_base_port + offset if cfg.metrics_base_port else 0

    entry = env_entry(cfg.env)
    skills = skill_discovery(cfg)
    configs = {
        "dynamics-learner": dataclasses.replace(cfg.learner, **common, metrics_port=port(1), models=cfg.models),
        "graph-evaluator": dataclasses.replace(cfg.evaluator, **common, metrics_port=port(2),
                                               induced_graphs=skills and cfg.policy.skild_graphs == "evaluator"),
        "dashboard": DashboardConfig(**common, metrics_port=port(3), http_host=LOOPBACK,
                                     http_port=cfg.dashboard_port, watch_run=cfg.run_id),
        "policy-learner": dataclasses.replace(
            cfg.policy, **common, metrics_port=port(4), algo=cfg.collector if cfg.collector != "random" else "ppo",
            scored=cfg.intrinsic != "none", skills=cfg.collector == "ppo" and bool(entry.skills),
            skild=skills, models=cfg.models),
        "intrinsic-reward": dataclasses.replace(cfg.intrinsic_reward, **common, metrics_port=port(5),
                                                reward=cfg.intrinsic if cfg.intrinsic != "none" else "preddiff"),
        "env-worker": worker_config(cfg, connect, worker_index),
    }
    configs["factor-extractor"] = dataclasses.replace(cfg.extractor, **common, metrics_port=port(6),
                                                      mode="latent-actions" if cfg.label_latent_actions else "slots")
    return {name: c if name == "env-worker" else dataclasses.replace(c, bus_credentials=credentials_path(cfg, name))
            for name, c in configs.items()}


def credentials_path(cfg: RunConfig, role: str) -> str:
    """The file ``role``'s processes read their bus credentials from ('' without ``--bus-auth``): a path
    in their environment, never the password (:mod:`services.bus.credentials`)."""
    return str(role_file(Path(cfg.run_dir).resolve(), role)) if cfg.bus_auth else ""


def prepare_bus_auth(cfg: RunConfig) -> RouterAuth | None:
    """With ``--bus-auth``: fresh credentials for every process of the run under ``<run_dir>/secrets`` and
    the router's access control (:mod:`services.bus.roles`); None without.

    One user per process, each pinned to its own keys: every service, and env-workers ``0`` ..
    ``--max-workers - 1``, all drawn now. eclipse-zenoh 1.10.2's router cannot reload its access control or
    its users while it runs (a session's configuration is fixed when it opens; restarting the router would
    drop every link), so a worker a scale request adds later takes one of these pre-drawn identities
    (:meth:`Supervisor.free_worker_index`)."""
    if not cfg.bus_auth:
        return None
    roles = run_roles(cfg.run_id, cfg.method, frames=cfg.worker.publish_frames, workers=cfg.max_workers,
                      latent=cfg.label_latent_actions)
    return write_run_secrets(cfg.run_dir, new_passwords(tuple(roles)), access_control(roles))


def learning_services(cfg: RunConfig) -> tuple[str, ...]:
    """The services besides env-workers and dashboard that ``cfg`` asks for (no graph-evaluator for
    a method that estimates no graph)."""
    method = get_method(cfg.method)
    graphs = method.global_graph is not None or method.local_graph is not None
    frames = cfg.worker.publish_frames or cfg.label_latent_actions
    return (("factor-extractor",) if frames else ()) + (("dynamics-learner",) + (("graph-evaluator",) if graphs else ())
            + (("policy-learner",) if cfg.collector != "random" or skill_discovery(cfg) else ())
            + (("intrinsic-reward",) if cfg.intrinsic != "none" else ()))


def worker_config(cfg: RunConfig, connect: str, index: int) -> EnvWorkerConfig:
    port = cfg.metrics_base_port + 10 + index if cfg.metrics_base_port else 0
    return dataclasses.replace(cfg.worker, **shared_settings(cfg), run_id=cfg.run_id, zenoh_connect=connect,
                               run_dir=cfg.run_dir, metrics_port=port, metrics_host=LOOPBACK, instance=str(index), env=cfg.env,
                               env_options=cfg.env_options, worker_index=index,
                               follow_policy=cfg.collector != "random", skild=skill_discovery(cfg),
                               frames_beside=cfg.label_latent_actions,
                               local_graphs=scores_local_graphs(cfg) or (skill_discovery(cfg) and
                                                                         cfg.policy.skild_graphs == "true"),
                               bus_credentials=credentials_path(cfg, instance_user("env-worker", index)))


def scores_local_graphs(cfg: RunConfig) -> bool:
    """Whether the run scores local graphs: the method estimates them, the env knows them, and the
    env scores them by default or ``--worker-local-graphs true`` asks (the workers then send them).
    Not over slots (``--worker-publish-frames``): the true local graphs are the objects'."""
    if cfg.worker.publish_frames:
        return False
    entry = env_entry(cfg.env)
    wanted = cfg.worker.local_graphs or entry.local_scoring
    return wanted and entry.has_local_truth and get_method(cfg.method).local_graph is not None


def env_kwargs(cfg: RunConfig) -> dict[str, Any]:
    """The constructor arguments of the run's environment."""
    return env_entry(cfg.env).kwargs(cfg.env_options)


def run_env_spec(cfg: RunConfig) -> EnvSpec:
    """The EnvSpec of the run's environment, as its first env-worker builds it."""
    return make_env(cfg.env, **env_kwargs(cfg)).unwrapped.env_spec()


def ports(cfg: RunConfig) -> dict[str, int]:
    """Every TCP port the run will listen on (127.0.0.1), by what listens there."""
    out = {"router (--router-port)": cfg.router_port}
    if cfg.dashboard_port:
        out["live page (--dashboard-port)"] = cfg.dashboard_port
    if cfg.metrics_base_port:
        configs = service_configs(cfg, "")
        for name in learning_services(cfg) + (("dashboard",) if cfg.dashboard_port else ()):
            out[f"{name} /metrics (--metrics-base-port)"] = configs[name].metrics_port
        for i in range(cfg.workers):
            out[f"env-worker {i} /metrics (--metrics-base-port)"] = worker_config(cfg, "", i).metrics_port
    return out


def check_ports_free(cfg: RunConfig) -> None:
    """``ValueError`` naming the first port the run needs that something else already holds."""
    for what, port in ports(cfg).items():
        if not 0 < port <= 65535:
            raise ValueError(f"{what}: port {port} is outside 1-65535")
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
            # As the router and the HTTP servers bind: a port whose old connections linger in TIME_WAIT
            # (a killed run's, started again at once) is free to them; one another socket listens on is not.
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind((LOOPBACK, port))
            except OSError as exc:
                raise ValueError(f"{what}: port {port} on {LOOPBACK} is in use ({exc.strerror}); "
                                 f"choose another or 0 where a free one may be picked") from None
