"""The map before initialization: random Gaussians in the bounding box (the reference's) or on the rays
of the pixels that fired in the initialization chunks (``gaussians.init_seeding``), and the same draws
again for the stages that refit a map from scratch (the rate check, the branches' restarts)."""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from evgs.config import GaussiansConfig
from evgs.slam.gaussians import Gaussians
from evgs.slam.state import SlamState, stage_seed
from evgs.slam.windows import EventData


def initial_gaussians(
    g: GaussiansConfig, data: EventData, m: int, generator: torch.Generator, first: int = 0
) -> Gaussians:
    """The map before initialization, seeded as ``gaussians.init_seeding`` says from chunks ``first`` to
    ``first + m``; the camera of chunk ``first`` is near the identity, so its optical axis is +z."""
    if g.init_seeding == "events":
        span = data.span(first, first + m)
        weights = seeding_weights(data.activity(span), g.init_min_events, g.init_fill_gap)
        spread = g.init_depth_spread or g.bounding_size
        depths = (g.init_depth - spread, g.init_depth + spread)
        if depths[0] <= 0:
            raise ValueError(
                f"gaussians.init_seeding = 'events' needs init_depth ({g.init_depth:g}) > the depth spread "
                f"({spread:g}; init_depth_spread, else bounding_size): the seeded depths must lie ahead"
            )
        return Gaussians.on_rays(
            g.num_init, weights, data.camera, depths, g.init_opacity, g.init_color, generator, g.init_tilt_deg
        )
    if g.init_tilt_deg:
        raise ValueError(
            "gaussians.init_tilt_deg tilts the 'events' seeding; the 'box' seeding has no slab to tilt"
        )
    gaussians = Gaussians.random(g.num_init, g.bounding_size, g.init_opacity, g.init_color, generator)
    with torch.no_grad():
        gaussians["means"][:, 2] += g.init_depth
    return gaussians


def seeding_generator(seed: int, seeding: int) -> torch.Generator:
    """The generator of seeding ``seeding``: 0 is the run's own (:func:`new_state`'s, from ``seed``), j > 0
    restart j's (``init.branch_restarts``)."""
    return torch.Generator().manual_seed(stage_seed(seed, "seeding", seeding) if seeding else seed)


def seeded_map(state: SlamState, generator: torch.Generator | None = None) -> Gaussians:
    """The map as ``state``'s seeding drew it (the same random draws), for refits that start afresh (the
    rate check: a kept restart's refits start from that restart's map); or as ``generator`` draws it
    (the branches' restarts)."""
    if generator is None:
        generator = seeding_generator(state.cfg.seed, state.seeding)
    return initial_gaussians(state.cfg.gaussians, state.data, state.num_init_chunks(), generator)


def seeding_weights(counts: Tensor, min_events: int, fill_gap: int) -> Tensor:
    """Per-pixel seeding weights from the init chunks' event counts: pixels with at least ``min_events``
    events weigh their count; with ``fill_gap`` > 0 the pixels they enclose once gaps of up to that many
    pixels are closed weigh ``min_events`` (a uniform face's events are only at its edges, so the face
    would stay empty; it is smooth, so few and larger Gaussians cover it)."""
    active = counts >= min_events
    weights = torch.where(active, counts, 0.0)
    if fill_gap > 0:
        mask = active.numpy()
        radius = (fill_gap + 1) // 2
        closed = ndimage.binary_closing(mask, np.ones((3, 3), bool), iterations=radius, border_value=0)
        inside = ndimage.binary_fill_holes(closed) & ~mask
        weights[torch.from_numpy(inside)] = float(min_events)
    return weights
