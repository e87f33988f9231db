"""`train.steps=by_views`: a fixed step count from the scene's training views: 1000 with at most 9, above that 1000
for every three views up to 10000 (10 or 11 views: 3000, 12: 4000, 24: 8000, 30 or more: 10000). The count is fixed
when the scene is loaded, so everything a fixed `train.steps=N` allows holds (schedules in absolute steps, a ramp).

Why this rule (the sparse-view presets, real captures, H100 and H200; docs/sparse_view.md): with 3 views the presets
keep 1000 steps (7 LLFF scenes, seeds 0-2: 1500 and 2000 +0.16 and +0.15 dB in the preset's mean at 1.5-2x the time;
along 10k-step runs 1000 was the best scored step), and every other measurement at 4-9 views (LLFF at 4 and 6, a real
3x3 light field's 9) is at 1000 steps; around four 360-degree captures, scored every 1000 steps along 10k-step runs, the
preset's mean was best at 4000 with 12 views (seed 0; 1000 and 10000 within 0.2 dB of it) and level from 4000 to 10000
with 24 (seeds 0-2; 1.1 dB under it at 1000). 10, 11, 13-23 and 25-29 views lie between measured counts; past 10k the
presets' depth-weight decay has ended and nothing was measured. The validation rule (`train.steps=auto`,
train/schedule.py) lost 0.55 dB to a fixed 10k with 24 views (3 captures, seeds 0-2)."""
from __future__ import annotations

KEYWORD = "by_views"
STEPS_PER_THREE_VIEWS = 1000
LEAST_STEPS = 1000
FEW_VIEWS = 9  # at most this many training views: LEAST_STEPS, the length every measurement there was made at
MOST_STEPS = 10_000


def steps_by_views(num_train_views: int) -> int:
    """The step count of `train.steps=by_views` with this many training views."""
    if num_train_views <= FEW_VIEWS:
        return LEAST_STEPS
    return min(MOST_STEPS, STEPS_PER_THREE_VIEWS * (num_train_views // 3))


def fixed_steps(setting, num_train_views: int) -> int:
    """A fixed `train.steps` (a number, or by_views counted from the training views) as the run's step count."""
    return steps_by_views(num_train_views) if setting == KEYWORD else int(setting)


def steps_note(setting, steps: int, num_train_views: int) -> str:
    """The start line's words for a fixed step count: by_views says how it counted."""
    if setting == KEYWORD:
        return f"{steps} steps (train.steps={KEYWORD}: {num_train_views} training views)"
    return f"{steps} steps"
