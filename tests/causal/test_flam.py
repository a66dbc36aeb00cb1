"""FLAM (ch. 8): FSQ round trips and straight-through gradients, the KL term against the closed form,
slot-wise masking of the per-slot dynamics, causal temporal attention, shapes, seeding and a short
fit of eq. 8.6."""
from __future__ import annotations

import math

import pytest
import torch
from torch.distributions import Normal, kl_divergence

from causal.flam import FLAM, FLAMConfig, LAMTrainer, MonolithicLAM, encode_clips, lam_loss, psnr, rollout
from causal.flam_nets import FSQ, FSQAutoencoder, gaussian_kl, grid_fourier_features

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CONFIG = FLAMConfig(num_slots=3, slot_dim=16, action_dim=4, iterations=2, levels=(5, 3, 7), batch_size=4)
TOKENS = 16


def _features(b: int = 2, t: int = 4, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return FSQ(CONFIG.levels)(torch.randn(b, t, TOKENS, len(CONFIG.levels), generator=generator))


def _flam(seed: int = 0) -> FLAM:
    torch.manual_seed(seed)
    return FLAM(CONFIG, TOKENS).eval()


def test_fsq_values_lie_on_the_level_grid_and_snap_is_idempotent() -> None:
    fsq = FSQ((5, 3, 7))
    q = fsq(torch.randn(500, 3) * 3)
    scaled = q * torch.tensor([2.0, 1.0, 3.0])
    torch.testing.assert_close(scaled, scaled.round())
    assert q.abs().max() <= 1.0
    for c, level in enumerate((5, 3, 7)):
        assert len(torch.unique(scaled[:, c])) == level
    torch.testing.assert_close(fsq.snap(q), q)
    torch.testing.assert_close(fsq.snap(q + 0.05), q)


def test_fsq_gradient_is_straight_through_the_rounding() -> None:
    fsq = FSQ((5, 5))
    z = torch.randn(64, 2, requires_grad=True)
    fsq(z).sum().backward()
    torch.testing.assert_close(z.grad, 1 - torch.tanh(z.detach()) ** 2)
    with pytest.raises(ValueError, match="odd"):
        FSQ((4, 5))


def test_autoencoder_tokens_are_quantised() -> None:
    torch.manual_seed(0)
    autoencoder = FSQAutoencoder((5, 5, 5, 5), width=8)
    frames = torch.randint(0, 256, (2, 3, 16, 16, 3), dtype=torch.uint8)
    tokens = encode_clips(autoencoder, frames)
    assert tokens.shape == (2, 3, 16, 4)
    torch.testing.assert_close(tokens * 2, (tokens * 2).round())
    assert autoencoder.decode(tokens[0], 4).shape == (3, 3, 16, 16)


def test_kl_matches_the_closed_form_and_sums_over_slots_in_the_loss() -> None:
    generator = torch.Generator().manual_seed(1)
    mu, log_sigma = torch.randn(6, 3, 4, generator=generator), torch.randn(6, 3, 4, generator=generator) * 0.5
    expected = kl_divergence(Normal(mu, log_sigma.exp()), Normal(0.0, 1.0)).sum(-1)
    torch.testing.assert_close(gaussian_kl(mu, log_sigma), expected)
    assert gaussian_kl(torch.zeros(2, 4), torch.zeros(2, 4)).abs().max() == 0
    features = _features(b=2, t=4)
    out = _flam()(features)
    _, terms = lam_loss(features, out, beta_kl=0.1)
    assert terms["kl"] == pytest.approx(float(gaussian_kl(out.mu, out.log_sigma).sum(-1).mean().detach()), rel=1e-5)
    total, _ = lam_loss(features, out, beta_kl=0.0)
    assert float(total.detach()) == pytest.approx(terms["prediction_sse"], rel=1e-5)


def test_latent_action_of_slot_k_only_moves_slot_k() -> None:
    model = _flam()
    current = torch.randn(5, CONFIG.num_slots, CONFIG.slot_dim)
    alpha = torch.randn(5, CONFIG.num_slots, CONFIG.action_dim, requires_grad=True)
    predicted = model.fdm(current, alpha)
    for i in range(CONFIG.num_slots):
        (grad,) = torch.autograd.grad(predicted[:, i].sum(), alpha, retain_graph=True)
        per_slot = grad.abs().sum(dim=(0, 2))
        assert per_slot[i] > 1e-4
        assert torch.all(per_slot[torch.arange(CONFIG.num_slots) != i] == 0)
    bumped = alpha.detach().clone()
    bumped[:, 1] += 1.0
    changed = (model.fdm(current, bumped) - predicted.detach()).abs().sum(dim=(0, 2))
    assert changed[1] > 1e-3 and changed[0] == 0 and changed[2] == 0


def test_slot_is_latent_action_reads_only_its_own_next_value() -> None:
    model = _flam()
    current = torch.randn(5, CONFIG.num_slots, CONFIG.slot_dim)
    nxt = torch.randn(5, CONFIG.num_slots, CONFIG.slot_dim)
    mu, _ = model.idm(current, nxt)
    bumped = nxt.clone()
    bumped[:, 2] += 1.0
    changed = (model.idm(current, bumped)[0] - mu).abs().sum(dim=(0, 2))
    assert changed[2] > 1e-3 and changed[0] == 0 and changed[1] == 0
    moved_current = current.clone()
    moved_current[:, 0] += 1.0
    assert ((model.idm(moved_current, nxt)[0] - mu).abs().sum(dim=(0, 2)) > 0).all()


def test_temporal_attention_is_causal() -> None:
    model = _flam()
    features = _features(b=1, t=5)
    slots, attention = model.factorizer(features)
    changed = features.clone()
    changed[:, 3] = -changed[:, 3]
    slots_changed, _ = model.factorizer(changed)
    torch.testing.assert_close(slots_changed[:, :3], slots[:, :3])
    assert (slots_changed[:, 3:] - slots[:, 3:]).abs().max() > 1e-4
    torch.testing.assert_close(attention.sum(dim=2), torch.ones(1, 5, TOKENS))


@pytest.mark.parametrize("cls", [FLAM, MonolithicLAM])
def test_shapes_rollout_and_seeded_determinism(cls: type) -> None:
    torch.manual_seed(3)
    model = cls(CONFIG, TOKENS).eval()
    features = _features(b=2, t=5)
    out = model(features, sample=False)
    assert out.predicted.shape == (2, 4, TOKENS, 3)
    alphas = model.infer(features)
    latent = CONFIG.num_slots * CONFIG.action_dim
    assert alphas.shape[:2] == (2, 4) and alphas[0, 0].numel() == latent
    predicted = rollout(model, features, FSQ(CONFIG.levels))
    assert predicted.shape == (2, 4, TOKENS, 3)
    on_grid = predicted * torch.tensor([2.0, 1.0, 3.0])
    torch.testing.assert_close(on_grid, on_grid.round())
    torch.manual_seed(3)
    again = cls(CONFIG, TOKENS).eval()
    torch.testing.assert_close(rollout(again, features, FSQ(CONFIG.levels)), predicted)


@pytest.mark.parametrize("ablation", [{}, {"temporal_attention": False}, {"coupling": "global"}])
def test_a_short_fit_of_eq_8_6_lowers_the_loss(ablation: dict) -> None:
    """FLAM and Table 8.5's ablations all learn."""
    model = _variant(**ablation).train()
    trainer = LAMTrainer(model, seed=0)
    features = _features(b=4, t=3, seed=5)
    first = trainer.update(features)["loss"]
    for _ in range(40):
        last = trainer.update(features)["loss"]
    assert last < 0.7 * first


def test_psnr_of_a_known_error_and_config_checks() -> None:
    target = torch.zeros(2, 3, 3, 4, 4)
    assert psnr(target + 0.1, target).tolist() == pytest.approx([20.0, 20.0], rel=1e-5)
    assert psnr(target, target).tolist() == pytest.approx([100.0, 100.0])
    with pytest.raises(ValueError):
        FLAMConfig(slot_dim=30)
    with pytest.raises(ValueError):
        FLAMConfig(beta_kl=-1.0)


def test_mask_prior_confines_each_slot_to_its_segment_and_anneals_away() -> None:
    model = _flam()
    features = _features(b=2, t=3)
    labels = torch.randint(CONFIG.num_slots, (2, 3, TOKENS), generator=torch.Generator().manual_seed(0))
    trainer = LAMTrainer(model, seed=0, mask_prior="annealed", total_updates=10)
    allowed = trainer.masks_for(labels)
    assert allowed is not None and allowed.shape == (2, 3, CONFIG.num_slots, TOKENS)
    torch.testing.assert_close(allowed.sum(dim=2), torch.ones(2, 3, TOKENS, dtype=torch.long))
    _, attention = model.factorizer(features, allowed)
    assert attention[~allowed].abs().max() < 1e-6
    trainer.updates = 10
    assert trainer.masks_for(labels).all()
    assert LAMTrainer(model, mask_prior="none").masks_for(labels) is None
    trainer.update(features, labels)
    with pytest.raises(ValueError, match="mask_prior"):
        LAMTrainer(model, mask_prior="always")


def test_foreground_prior_keeps_the_background_slot_apart_and_lets_the_others_share_objects() -> None:
    model = _flam()
    labels = torch.randint(3, (2, 3, TOKENS), generator=torch.Generator().manual_seed(1))
    trainer = LAMTrainer(model, seed=0, mask_prior="foreground", total_updates=10)
    allowed = trainer.masks_for(labels)
    objects = labels > 0
    assert torch.equal(allowed[:, :, 0], ~objects)  # the background's slot: background tokens only
    for k in range(1, CONFIG.num_slots):  # every other slot: any object's tokens, whichever segment
        assert torch.equal(allowed[:, :, k], objects)
    trainer.updates = 10
    assert trainer.masks_for(labels).all()  # annealed away like the segment prior


def test_binding_term_is_the_cross_entropy_of_the_unmasked_attention_against_the_mask() -> None:
    model = _flam()
    features = _features(b=2, t=3)
    labels = torch.randint(CONFIG.num_slots, (2, 3, TOKENS), generator=torch.Generator().manual_seed(2))
    allowed = torch.nn.functional.one_hot(labels, CONFIG.num_slots).permute(0, 1, 3, 2).bool()
    # by hand, one iteration from the initial slots: -log of the unmasked softmax at the label's slot
    factorizer = torch.nn.Module.__new__(type(model.factorizer))
    factorizer.__dict__.update(model.factorizer.__dict__)
    factorizer.iterations = 1
    tokens = model.factorizer.norm_tokens(model.factorizer.embed(features)).flatten(0, 1)
    queries = model.factorizer.to_q(model.factorizer.norm_slots(model.factorizer.initial))
    logits = torch.einsum("kd,mnd->mkn", queries, model.factorizer.to_k(tokens)) * model.factorizer.scale
    cross_entropy = -logits.log_softmax(dim=1).gather(1, labels.flatten(0, 1)[:, None])[:, 0]  # [frames, n]
    per_segment = [cross_entropy[f][labels.flatten(0, 1)[f] == k].mean()  # each segment counts alike
                   for f in range(len(cross_entropy)) for k in range(CONFIG.num_slots)
                   if (labels.flatten(0, 1)[f] == k).any()]
    expected = torch.stack(per_segment).mean()
    torch.testing.assert_close(factorizer.bind(features, allowed)[2], expected)
    # nothing to learn where no mask is given or every slot is allowed (a dropped mask)
    with torch.no_grad():
        assert float(model.factorizer.bind(features)[2]) == 0.0
        assert float(model.factorizer.bind(features, torch.ones_like(allowed))[2]) == 0.0
        # a dropped clip adds nothing and does not dilute the others
        dropped = allowed.clone()
        dropped[1] = True
        kept = factorizer.bind(features[:1], allowed[:1])[2]
        torch.testing.assert_close(factorizer.bind(features, dropped)[2], kept)
        assert model(features).binding is None


def test_binding_weight_teaches_the_slots_to_bind_without_the_mask() -> None:
    features = _features(b=4, t=3)
    labels = (features[..., 0] > -0.25).long() + (features[..., 0] > 0.25).long()  # a token's segment: its look
    allowed = torch.nn.functional.one_hot(labels, CONFIG.num_slots).permute(0, 1, 3, 2).bool()
    with torch.no_grad():
        start = float(_flam().factorizer.bind(features, allowed)[2])
    ends = []
    for weight in (0.0, 1.0):
        torch.manual_seed(0)
        model = FLAM(FLAMConfig(**{**CONFIG.__dict__, "mask_binding": weight, "lr": 3e-3}), TOKENS)
        trainer = LAMTrainer(model, seed=0, mask_prior="annealed", total_updates=10**9)  # masks kept
        for _ in range(60):
            terms = trainer.update(features, labels)
        assert "mask_binding_ce" in terms
        with torch.no_grad():
            ends.append(float(model.factorizer.bind(features, allowed)[2]))
    # the restricted attention alone gives the unmasked attention no pull towards the labels
    assert ends[1] < 0.5 * start and ends[1] < 0.5 * ends[0]
    with pytest.raises(ValueError, match="mask_binding"):
        FLAMConfig(mask_binding=-1.0)


def test_slot_reconstruction_term_is_added_when_weighted() -> None:
    torch.manual_seed(0)
    model = FLAM(FLAMConfig(**{**CONFIG.__dict__, "slot_reconstruction": 0.5}), TOKENS).eval()
    features = _features(b=2, t=3)
    out = model(features, sample=False)
    assert out.reconstructed is not None and out.reconstructed.shape == features.shape
    loss, terms = lam_loss(features, out, beta_kl=0.0, slot_reconstruction=0.5)
    assert float(loss.detach()) == pytest.approx(terms["prediction_sse"] + 0.5 * terms["slot_reconstruction_sse"], rel=1e-5)
    assert _flam()(features).reconstructed is None


def test_fourier_positions_are_distinct_and_the_broadcast_aggregator_mixes_slots() -> None:
    fourier = grid_fourier_features(16)
    assert fourier.shape == (16, 8)
    distances = torch.cdist(fourier, fourier) + torch.eye(16)
    assert distances.min() > 0.1
    with pytest.raises(ValueError, match="square"):
        grid_fourier_features(15)
    torch.manual_seed(0)
    model = FLAM(FLAMConfig(**{**CONFIG.__dict__, "aggregator": "broadcast"}), TOKENS).eval()
    features = _features(b=2, t=3)
    assert model(features, sample=False).predicted.shape == (2, 2, TOKENS, 3)
    slots = torch.randn(4, CONFIG.num_slots, CONFIG.slot_dim)
    one_slot = model.aggregator(features[0, :4], slots[:, :1])
    out = model.aggregator.mlp(slots[:, :1, None, :] + model.aggregator.position(model.aggregator.fourier))
    torch.testing.assert_close(one_slot, out[:, 0, :, :-1])
    with pytest.raises(ValueError, match="aggregator"):
        FLAMConfig(aggregator="sum")


def _variant(**changes) -> FLAM:
    torch.manual_seed(0)
    return FLAM(FLAMConfig(**{**CONFIG.__dict__, **changes}), TOKENS).eval()


def test_global_coupling_lets_every_slot_read_every_latent_action_and_next_slot() -> None:
    """Table 8.5's Global-Coupled FLAM: the FDM's slot i reads every alpha^j and the IDM's alpha^i every
    slot at t+1 (the per-slot model's independence, tested above, is what it gives up)."""
    model = _variant(coupling="global")
    current = torch.randn(5, CONFIG.num_slots, CONFIG.slot_dim)
    alpha = torch.randn(5, CONFIG.num_slots, CONFIG.action_dim, requires_grad=True)
    predicted = model.fdm(current, alpha)
    assert predicted.shape == current.shape
    for i in range(CONFIG.num_slots):
        (grad,) = torch.autograd.grad(predicted[:, i].sum(), alpha, retain_graph=True)
        assert (grad.abs().sum(dim=(0, 2)) > 1e-6).all()
    nxt = torch.randn(5, CONFIG.num_slots, CONFIG.slot_dim)
    mu, _ = model.idm(current, nxt)
    bumped = nxt.clone()
    bumped[:, 2] += torch.randn(5, CONFIG.slot_dim)  # not a constant shift: the keys' LayerNorm removes those
    assert ((model.idm(current, bumped)[0] - mu).abs().sum(dim=(0, 2)) > 1e-4).all()
    assert model(_features(b=2, t=3), sample=False).predicted.shape == (2, 2, TOKENS, 3)
    with pytest.raises(ValueError, match="coupling"):
        FLAMConfig(coupling="pairwise")


def test_without_temporal_attention_slots_start_from_the_previous_frames() -> None:
    """Table 8.5's "w/o temporal attention" (SAVi-style): no temporal block; frame t's slots depend on
    frames up to t only, frame 0's are a single frame's slot attention from the learned initial slots."""
    model = _variant(temporal_attention=False)
    assert model.factorizer.temporal is None
    features = _features(b=1, t=5)
    slots, attention = model.factorizer(features)
    assert slots.shape == (1, 5, CONFIG.num_slots, CONFIG.slot_dim)
    torch.testing.assert_close(attention.sum(dim=2), torch.ones(1, 5, TOKENS))
    single, _ = model.factorizer(features[:, :1])
    torch.testing.assert_close(single[:, 0], slots[:, 0])
    changed = features.clone()
    changed[:, 3] = -changed[:, 3]
    slots_changed, _ = model.factorizer(changed)
    torch.testing.assert_close(slots_changed[:, :3], slots[:, :3])
    assert (slots_changed[:, 3:] - slots[:, 3:]).abs().amax(dim=(0, 2, 3)).min() > 1e-4  # frame 4 through frame 3's slots
    earlier = features.clone()
    earlier[:, 0] = -earlier[:, 0]
    assert (model.factorizer(earlier)[0][:, 1] - slots[:, 1]).abs().max() > 1e-4


def test_the_default_factorizer_is_unchanged_by_the_ablation_switch() -> None:
    """The per-slot, temporal-attention FLAM (the default) builds the same parameters as before the
    ablations existed: a checkpoint of it loads into ``FLAMConfig()``'s model and gives the same slots."""
    model = _variant()
    names = set(model.state_dict())
    assert any(name.startswith("factorizer.temporal.") for name in names)
    ablated = _variant(temporal_attention=False)
    assert not any(name.startswith("factorizer.temporal.") for name in ablated.state_dict())
    again = FLAM(CONFIG, TOKENS).eval()
    again.load_state_dict(model.state_dict())
    features = _features(b=2, t=4)
    torch.testing.assert_close(again.factorizer(features)[0], model.factorizer(features)[0])


def test_cosine_decay_sets_each_updates_learning_rate() -> None:
    model = _variant(lr=2e-3, lr_final=1e-4, lr_decay_updates=4)
    trainer = LAMTrainer(model, seed=0)
    features = _features(b=2, t=3)
    seen = []
    for _ in range(6):
        trainer.update(features)
        seen.append(trainer.optimizer.param_groups[0]["lr"])
    # update u runs at lr_final + (lr - lr_final) (1 + cos(pi u / 4)) / 2, lr_final from u = 4 on
    expected = [1e-4 + 0.5 * 1.9e-3 * (1 + math.cos(math.pi * u / 4)) for u in range(4)] + [1e-4, 1e-4]
    assert seen == pytest.approx(expected, rel=1e-9)
    constant = LAMTrainer(_variant(lr=2e-3), seed=0)
    constant.update(features)
    assert constant.optimizer.param_groups[0]["lr"] == 2e-3
    with pytest.raises(ValueError, match="lr_decay_updates"):
        FLAMConfig(lr_decay_updates=-1)


def test_a_static_background_slot_has_no_latent_action_and_costs_no_kl() -> None:
    """``static_background``: slot 0's posterior is N(0, I) in training and inference (so its KL is 0)
    and its alpha is 0, so the prediction does not depend on anything the IDM reads for slot 0;
    the other slots' latents are the plain model's."""
    import dataclasses
    features = _features()
    torch.manual_seed(0)
    static = FLAM(dataclasses.replace(CONFIG, static_background=True), TOKENS).eval()
    torch.manual_seed(0)
    plain = FLAM(CONFIG, TOKENS).eval()
    out, reference = static(features, sample=False), plain(features, sample=False)
    assert torch.all(out.mu[..., 0, :] == 0) and torch.all(out.log_sigma[..., 0, :] == 0)
    assert float(gaussian_kl(out.mu[..., :1, :], out.log_sigma[..., :1, :]).detach().abs().sum()) == 0.0
    torch.testing.assert_close(out.mu[..., 1:, :], reference.mu[..., 1:, :])
    assert torch.all(static.infer(features)[..., 0, :] == 0)
    seen = []
    static.fdm.register_forward_pre_hook(lambda module, args: seen.append(args[1].detach().clone()))
    torch.manual_seed(1)
    static(features, sample=True)  # sampling draws noise for every slot; slot 0's must not reach the FDM
    assert torch.all(seen[0][:, 0] == 0) and bool((seen[0][:, 1:] != 0).any())


def test_quantised_latent_actions_are_codes_without_noise_or_kl() -> None:
    """``action_levels``: each slot's alpha is its IDM mean on the FSQ grid (5 x 3 codes here), the
    same with and without sampling; the trainer's loss is the prediction error alone, and the
    gradient reaches the IDM through the straight-through rounding."""
    import dataclasses
    config = dataclasses.replace(CONFIG, action_dim=2, action_levels=(5, 3))
    torch.manual_seed(0)
    model = FLAM(config, TOKENS).train()
    features = _features(b=2, t=4)
    out = model(features, sample=True)
    grid = out.mu * torch.tensor([2.0, 1.0])
    torch.testing.assert_close(grid, grid.round())
    assert torch.all(out.log_sigma == 0)
    torch.testing.assert_close(model(features, sample=True).predicted, out.predicted)
    torch.testing.assert_close(model.infer(features), out.mu)
    trainer = LAMTrainer(model, seed=0)
    before = [p.detach().clone() for p in model.idm.to_mu.parameters()]
    terms = trainer.update(features)
    assert terms["loss"] == pytest.approx(terms["prediction_sse"], rel=1e-6)
    assert any(not torch.equal(b, a) for b, a in zip(before, model.idm.to_mu.parameters()))
    with pytest.raises(ValueError, match="action_dim"):
        dataclasses.replace(CONFIG, action_levels=(5, 3))
    with pytest.raises(ValueError, match="FLAM's alone"):
        MonolithicLAM(config, TOKENS)
