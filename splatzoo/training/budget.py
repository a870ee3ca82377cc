"""A byte budget (TrainConfig.max_bytes): the model ends the run no larger than its budget, stored at the run's
precision, by giving up whatever costs the images least.

From FROM to UNTIL of the run, STEPS times, the model sheds a share of what it holds over the budget, so that it
meets the budget at UNTIL and trains on without the shed parts for the rest of the run. Each time, what the model
judges worth nothing goes first (SplatModel.shed_free: adaptive waves' measured pruning), then every way the model
offers (SplatModel.shedding_options: its weakest surfels; beta-gabor and gabor-adaptive also their faintest waves)
is rendered on the trainer's probe views, and the one that raises their error least is taken, a quarter of the
shedding's excess at a time (CHOICES), so that one shedding can give up some waves and some surfels. So a model that
starts as rich as its count allows keeps waves where they are worth more than the surfels they cost, and becomes a
plain 2DGS model of fewer surfels where they are not. After UNTIL the budget is only checked (nothing grows a model
with a fixed count).
"""
from __future__ import annotations

import copy
import math

from ..zoo import stored_bytes

FROM = 0.5    # the first shedding, as a fraction of the run
UNTIL = 0.85  # the model is within its budget from here on
STEPS = 8     # sheddings between FROM and UNTIL
CHOICES = 4   # each choice frees at most 1/CHOICES of the shedding's excess: one choice for all of it takes the
              # whole cut in one kind (boots at 256 px, 100%: the last shedding took 1,869 waves at once and lost 0.9
              # dB against four choices; BENCHMARKS.md, "Budgeted runs start with twice what fits")
MAX_ROUNDS = 16  # choices per shedding at most (CHOICES, and what a way that frees less than it asked leaves over)


def start_count(net, max_bytes: int, precision: str) -> int:
    """The most surfels a model like `net` holds under a budget of `max_bytes` before it sheds: its multiple
    (SplatModel.budget_start) of the rows the budget holds plain (SplatModel.shed_richness) at `precision`. A run
    under a budget starts with no more (its scene's points subsampled, as `compare --budgets` starts every run), and
    densification grows to no more."""
    fit = plain_count(net, max_bytes, precision)
    return max(1, math.ceil(net.budget_start(fit) * fit))


def plain_count(net, max_bytes: int, precision: str) -> int:
    """The rows of a model like `net`, all plain (SplatModel.shed_richness), that `max_bytes` holds at `precision`
    (the file's fixed bytes aside)."""
    plain = copy.deepcopy(net).shed_richness().stored_row_bytes(precision)
    per = float(plain.mean()) if plain.numel() else 1.0
    return int(max_bytes // max(per, 1.0))


def shedding_steps(iterations: int) -> list[int]:
    """The iterations at which the budget is enforced: STEPS between FROM and UNTIL, then the last one."""
    first, last = FROM * iterations, UNTIL * iterations
    steps = {max(1, math.ceil(first + (last - first) * i / (STEPS - 1))) for i in range(STEPS)}
    return sorted(steps | {iterations})


def share_due(step: int, iterations: int) -> float:
    """The share of the model's excess over the budget to shed at `step` (1 from UNTIL on)."""
    steps = [s for s in shedding_steps(iterations) if s <= max(UNTIL * iterations, 1)] or [iterations]
    later = sum(s >= step for s in steps)
    return 1.0 if later <= 1 else 1.0 / later


def enforce(net, optimizer, probe_error, max_bytes: int, precision: str, share: float) -> dict:
    """Shed `share` of what the model holds over `max_bytes` (all of it when share is 1), choosing each time the way
    whose preview raises the probe views' error least. Returns {"stored_bytes", "shed": [what, ...]}."""
    freed = net.shed_free(optimizer)  # what the model judges worth nothing goes first, whatever the budget
    shed = [f"{freed['removed']} waves worth nothing"] if freed and freed.get("removed") else []
    size = stored_bytes(net, precision)
    target = max_bytes + (1 - share) * max(0, size - max_bytes)
    portion = math.ceil(max(0, size - target) / CHOICES)
    for _ in range(MAX_ROUNDS):
        if size <= target:
            break
        options = net.shedding_options(min(portion, math.ceil(size - target)), precision, optimizer)
        if not options:
            break
        errors = [probe_error(o.preview) if probe_error is not None else 0.0 for o in options]
        # the least error; on a tie the model's own richness (listed after its surfels) goes first
        best = options[min(reversed(range(len(options))), key=errors.__getitem__)]
        best.apply()
        shed.append(best.what)
        size = stored_bytes(net, precision)
    return {"stored_bytes": size, "shed": shed}
