"""A rendering stage: shared rays give the same APS as separate rays, and inert samples change nothing."""

from __future__ import annotations

import torch

from rflscm.fields import PassiveMedium, TensorVM
from rflscm.models.rflscm.config import MIN_WEIGHT, DecoderConfig, RenderConfig
from rflscm.models.rflscm.fields import Queries, RadianceDecoder, RadianceStage, RayBatch, SceneFrame, VMFields
from rflscm.render import RaySamples, gather_samples, select_samples

LO, HI = (-50.0, -50.0, 0.0), (50.0, 50.0, 30.0)


def make_stage(inputs: str = "offset+grid") -> RadianceStage:
    torch.manual_seed(0)
    frame = SceneFrame(LO, HI, num_samples=12, reference_wavelength_m=0.1, reference_distance_m=40.0)
    lo, hi = torch.tensor(LO), torch.tensor(HI)
    medium = PassiveMedium(0.1, 4.0)
    delta = TensorVM(lo, hi, (6, 6, 4), 2, medium.num_channels, "per_channel", init_scale=0.5)
    features = TensorVM(lo, hi, (6, 6, 4), 2, 4, "per_component", init_scale=0.5)
    decoder = RadianceDecoder(DecoderConfig(hidden=8, inputs=inputs), 4, frame, 4.0)
    return RadianceStage(VMFields(delta, features), medium, decoder, RenderConfig(step_m=4.0))


def rays_for(n: int) -> RayBatch:
    g = torch.Generator().manual_seed(1)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return RayBatch(
        torch.zeros(n, 3) + torch.tensor([0.0, 0.0, 20.0]), d, torch.full((n,), 0.1), torch.full((n,), 0.05)
    )


def test_shared_rays_equal_separate_rays() -> None:
    stage = make_stage()
    phi = (torch.rand(3, 12, generator=torch.Generator().manual_seed(2)) > 0.5) * torch.rand(3, 12)
    samples = select_samples(phi)
    grids = torch.tensor([[10.0, 5.0, 1.5], [-20.0, 7.0, 1.5], [3.0, -30.0, 1.5], [0.0, 0.0, 1.5]])
    rays = rays_for(3)
    shared = stage(rays, gather_samples(samples, torch.arange(3)), Queries(torch.tensor([0, 0, 2, 1]), grids))
    # the same four queries with one private copy of the ray each
    copies = torch.tensor([0, 0, 2, 1])
    separate_rays = RayBatch(
        rays.origin[copies], rays.direction[copies], rays.wavelength_m[copies], rays.radius_rad[copies]
    )
    separate = stage(separate_rays, gather_samples(samples, copies), Queries(torch.arange(4), grids))
    assert torch.allclose(shared, separate, rtol=1e-5, atol=1e-12)
    assert shared[0] != shared[1]  # same ray, different grids


def test_inert_samples_change_nothing() -> None:
    stage = make_stage("paper")
    phi = torch.zeros(1, 12)
    phi[0, 5:7] = torch.tensor([0.7, 1.0])
    everything = RaySamples(torch.tensor([0, 12]), torch.arange(12, dtype=torch.int32), phi[0])
    queries = Queries(torch.tensor([0]), torch.tensor([[10.0, 5.0, 1.5]]))
    full = stage(rays_for(1), gather_samples(everything, torch.tensor([0])), queries)
    sparse = stage(rays_for(1), gather_samples(select_samples(phi), torch.tensor([0])), queries)
    assert torch.allclose(full, sparse, rtol=1e-5) and float(full.detach()) > 0


def test_early_termination_drops_only_negligible_samples() -> None:
    """Samples below ``MIN_WEIGHT`` are skipped: the APS changes by less than their possible share."""
    stage = make_stage()
    with torch.no_grad():  # an opaque scene: most samples lie deep behind the first walls
        for p in stage.fields.delta_module().parameters():
            p.mul_(6.0)
    phi = torch.rand(3, 12, generator=torch.Generator().manual_seed(3))
    samples = select_samples(phi)
    rays, queries = (
        rays_for(3),
        Queries(torch.tensor([0, 1, 2]), torch.tensor([[10.0, 5.0, 1.5], [-20.0, 7.0, 1.5], [3.0, -30.0, 1.5]])),
    )
    stage.min_weight = 0.0
    evals0 = stage.decoder_evals
    full = stage(rays, gather_samples(samples, torch.arange(3)), queries)
    all_evals = stage.decoder_evals - evals0
    stage.min_weight = MIN_WEIGHT
    evals0 = stage.decoder_evals
    pruned = stage(rays, gather_samples(samples, torch.arange(3)), queries)
    assert stage.decoder_evals - evals0 < all_evals
    assert torch.allclose(pruned, full, rtol=1e-3, atol=0.0)


def test_the_pair_inputs_are_the_concatenated_encodings_and_the_decoder_still_learns() -> None:
    from rflscm.fields import positional_encoding
    from rflscm.fields.surfaces import specularity
    from rflscm.models.rflscm.config import DIR_FREQS, POS_FREQS, SPECULAR_POWERS

    decoder = make_stage().decoder
    g = torch.Generator().manual_seed(3)
    to_grid = torch.nn.functional.normalize(torch.randn(400, 3, generator=g), dim=-1)
    direction = torch.nn.functional.normalize(torch.randn(400, 3, generator=g), dim=-1)
    dist, along, miss = (
        50 * torch.rand(400, generator=g),
        80 * torch.rand(400, generator=g),
        torch.rand(400, generator=g),
    )
    surface = torch.rand(400, 6, generator=g)
    got = decoder._pair_inputs(to_grid, dist, along, miss, direction, surface)
    # the reference: each encoding made on its own and concatenated
    scale = torch.log1p(torch.tensor(decoder.frame.reference_distance_m / decoder.step_m))
    logs = torch.stack((torch.log1p(dist / 4.0), torch.log1p(along / 4.0), miss), -1) / scale
    half = torch.nn.functional.normalize(to_grid - direction, dim=-1)
    spec = specularity(surface, half).clamp(0.0, 1.0)
    want = torch.cat(
        [
            positional_encoding(to_grid, DIR_FREQS),
            positional_encoding(half, DIR_FREQS),
            positional_encoding(logs, POS_FREQS),
            torch.stack([spec**p for p in SPECULAR_POWERS], -1),
        ],
        -1,
    )
    torch.testing.assert_close(got, want, atol=3e-5, rtol=1e-5)
    assert (
        float(decoder._pair_inputs(to_grid, dist, along, miss, direction, None)[:, -len(SPECULAR_POWERS) :].abs().max())
        == 0.0
    )
    # the in-place sums and ReLUs keep the graph: a step on the rendered power moves every decoder weight
    stage = make_stage()
    phi = (torch.rand(3, 12, generator=torch.Generator().manual_seed(2)) > 0.3) * torch.rand(3, 12)
    queries = Queries(
        torch.tensor([0, 1, 2, 2]),
        torch.tensor([[10.0, 5.0, 1.5], [-20.0, 7.0, 1.5], [3.0, -30.0, 1.5], [0.0, 0.0, 1.5]]),
    )
    power = stage(rays_for(3), gather_samples(select_samples(phi), torch.arange(3)), queries)
    power.sum().backward()
    for name, p in stage.decoder.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name
    assert all(float(p.grad.abs().sum()) > 0 for p in (stage.decoder.pair_in.weight, stage.decoder.sample_in.weight))


def test_inference_in_decoder_blocks_equals_the_training_path(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Without gradients the decoder runs ``DECODER_BLOCK`` (query, sample) pairs at a time (issue 29): the same
    values as the training path's one pass (block sizes that split rays and queries included), to the bit where a
    block holds several pairs; a block of one pair may take the BLAS's matrix-vector kernel, which on some CPUs (an
    AMD EPYC) rounds one value one float32 ulp apart."""
    import rflscm.models.rflscm.fields as fields_module

    phi = (torch.rand(5, 12, generator=torch.Generator().manual_seed(3)) > 0.3) * torch.rand(5, 12)
    samples = select_samples(phi)
    g = torch.Generator().manual_seed(4)
    grids = torch.cat((torch.rand(9, 2, generator=g) * 80.0 - 40.0, torch.full((9, 1), 1.5)), 1)
    queries = Queries(torch.tensor([0, 0, 1, 2, 2, 2, 3, 4, 4]), grids)
    for inputs in ("paper", "offset", "offset+grid"):
        stage = make_stage(inputs)
        stage.min_weight = 0.0
        with torch.enable_grad():
            trained = stage(rays_for(5), gather_samples(samples, torch.arange(5)), queries).detach()
        for block in (1, 3, 7, 10**6):
            monkeypatch.setattr(fields_module, "DECODER_BLOCK", block)
            with torch.no_grad():
                inferred = stage(rays_for(5), gather_samples(samples, torch.arange(5)), queries)
            if block > 1:
                assert torch.equal(inferred, trained), (inputs, block)
            torch.testing.assert_close(inferred, trained, rtol=1e-6, atol=0.0)
        assert bool((trained > 0).all())
