# ---
# jupyter:
#   jupytext:
#     notebook_metadata_filter: -jupytext.text_representation.jupytext_version
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 05 · A Barrett WAM playing table tennis in SAPIEN
#
# Thesis Sec. 3.5 and 4.3: a 7-DoF Barrett WAM hangs above its end of the table and returns the
# balls of a human opponent. It has three hitting movements (forehand, middle, backhand), each with
# its own *preparation pose*. Because its accelerations and torques are limited, a movement can only
# return balls that arrive near its preparation pose, and it has to be initiated **before the
# opponent hits the ball** - which is why the thesis infers the opponent's intended target from the
# opponent's movement.
#
# This notebook shows the pieces of `hgpdm_torch.robots`:
#
# 1. the simulated opponent, whose strokes are driven by an intended target on the robot's hitting
#    plane;
# 2. one stroke of the robot simulated in SAPIEN (PhysX, 1 ms steps), drawn from forward kinematics;
# 3. the hitting regions that emerge from the limits and the timing (the analogue of the thesis's
#    Fig. 3.8);
# 4. what happens when a movement starts too late.

# %%
import os
import tempfile

import matplotlib.pyplot as plt
import numpy as np
import torch

from hgpdm_torch.robots import WAM
from hgpdm_torch.robots.table_tennis import ball as B
from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.robots.table_tennis.draw import (
    MOVEMENT_COLORS,
    draw_stroke,
    draw_table,
    plot_hitting_regions,
)
from hgpdm_torch.robots.table_tennis.opponent import sample_strokes
from hgpdm_torch.robots.table_tennis.strokes import MOVEMENTS
from hgpdm_torch.robots.table_tennis.trials import evaluate, hitting_regions, make_trials

torch.set_default_dtype(torch.float64)
SMOKE = os.environ.get("HGPDM_SMOKE", "0") == "1"
# %matplotlib inline

# %% [markdown]
# ## The opponent
#
# Each stroke of the simulated opponent is driven by an intended target $x$ on the robot's virtual
# hitting plane, 0.8 m behind the table. The racket moves ready pose -> backswing -> contact; the
# returned ball is computed from the racket state at contact with the ball model, so the racket the
# robot observes is consistent with where the ball goes. Below: the racket paths over the last 400
# ms (coloured by the target) and the returned balls.

# %%
strokes = sample_strokes(4 if SMOKE else 12, generator=torch.Generator().manual_seed(0))
t_plane, at_plane, _ = B.predict_plane_crossing(strokes.ball_after_hit, geo.HITTING_PLANE_Y)
flights = B.simulate(strokes.ball_after_hit, float(t_plane.max()), 0.01)
cmap = plt.get_cmap("coolwarm")
fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 5), gridspec_kw={"width_ratios": [1, 1.3]})
draw_table(ax)
for i, x in enumerate(strokes.targets.tolist()):
    c = cmap((x + 1.2) / 2.4)
    racket = strokes.racket.pos[i].numpy()
    ax.plot(racket[:, 0], racket[:, 1], color=c, lw=2.5)
    ax.plot(*racket[0, :2], "o", color=c, ms=4)  # 400 ms before the hit
    keep = flights.times <= t_plane[i]
    ax.plot(flights.pos[i][keep][:, 0], flights.pos[i][keep][:, 1], color=c, lw=0.8)
ax.set_title("top view: opponent racket (thick, dot = 400 ms\nbefore the hit) and returned balls",
             fontsize=9)
ax2.scatter(strokes.targets, at_plane.pos[:, 2], c=strokes.targets, cmap=cmap, vmin=-1.2, vmax=1.2)
ax2.set_xlabel("target x on the hitting plane [m]")
ax2.set_ylabel("ball height at the plane [m]")
ax2.set_title(f"balls reach the plane {t_plane.min():.2f}-{t_plane.max():.2f} s after the hit",
              fontsize=9)
plt.tight_layout()
plt.show()

# %% [markdown]
# ## One stroke of each movement
#
# Time 0 is the opponent's hit. Each movement is initiated 240 ms before it: the arm swings from the
# awaiting pose to the movement's preparation pose (as fast as the joint velocity and acceleration
# limits allow: 0.2 s for the middle pose, 0.65-0.9 s for the side poses). 160 ms after the
# opponent's hit the ball's flight is predictable; once the arm is prepared, and no earlier than
# 0.35 s before the ball reaches the hitting plane, it swings through the predicted hitting point
# with the racket velocity and normal that return the ball to the opponent's court. Joint
# velocities, accelerations and torques are limited, so a plan that asks for more is not followed
# and the racket misses. The arm is drawn from forward kinematics at the hit; the orange lines are
# the incoming ball and the return.

# %%
wam = WAM()
trials = make_trials(3 if SMOKE else 6, seed=1)
# for each movement the trial whose target lies closest to the middle of its region
centres = {"backhand": -0.6, "middle": 0.0, "forehand": 0.5}
picks = {m: int(np.argmin(np.abs(trials.targets.numpy() - c))) for m, c in centres.items()}
results = {}
fig = plt.figure(figsize=(13, 4.6))
for k, (movement, i) in enumerate(picks.items()):
    out = results[movement] = evaluate(trials[i], movement, -0.24)
    ax = fig.add_subplot(1, 3, k + 1, projection="3d")
    draw_table(ax)
    draw_stroke(ax, out, wam, color=MOVEMENT_COLORS[movement])
    ax.set(xlim=(-1.3, 1.3), ylim=(-2.8, 1.6), zlim=(0.0, 1.8))
    ax.set_box_aspect((2.6, 4.4, 1.8))
    ax.view_init(20, -35)
    verdict = "returned" if out.success else ("hit, not legal" if out.hit else "missed")
    ax.set_title(f"{movement}, target x = {trials.targets[i]:+.2f} m: {verdict}", fontsize=9)
plt.tight_layout()
plt.show()

# %% [markdown]
# ## Hitting regions
#
# Every trial is played with every movement, started 240 ms before the opponent's hit, in SAPIEN,
# and the legal returns are averaged in bins of the true target. Nothing in the code states where a
# movement can hit: the regions come from the preparation poses, the joint limits and the time left.
# The forehand covers the robot's right (+x), the backhand its left, the middle one lies in between,
# and the three overlap - as in the thesis's Fig. 3.8. (With `HGPDM_SMOKE=1` only a handful of
# trials are played, so the curves are coarse.)

# %%
n_trials = 6 if SMOKE else 90
region_trials = make_trials(n_trials, seed=2)
bins = np.linspace(-1.2, 1.2, 5 if SMOKE else 9)
cache = tempfile.mkdtemp()  # reward_table caches on disk; a fresh folder always simulates
centers, rates, counts = hitting_regions(region_trials, -0.24, bins, cache_dir=cache,
                                         progress=False)
fig, ax = plt.subplots(figsize=(7, 3.8))
plot_hitting_regions(ax, centers, rates, counts, start_time=-0.24)
plt.tight_layout()
plt.show()
for name in MOVEMENTS:
    print(f"{name:9s}", np.round(rates[name], 2))

# %% [markdown]
# ## Starting too late
#
# The later a movement is initiated, the later the arm reaches its preparation pose and the less
# time is left for the swing. The side movements need the longest preparation, so they are the first
# to lose balls when initiated after the opponent's hit; every movement fails when started 150 ms
# before the ball reaches the plane.

# %%
# a movement that returned its ball when started 240 ms early (the forehand if it did)
movement = next((m for m in ("forehand", "backhand", "middle") if results[m].success), "middle")
trial = trials[picks[movement]]
t_cross, _, _ = B.predict_plane_crossing(trial.ball_after_hit, geo.HITTING_PLANE_Y)
for t0 in [-0.24, 0.0, 0.2, float(t_cross) - 0.15]:
    out = evaluate(trial, movement, t0)
    print(f"{movement} started at {t0:+.2f} s (ball at the plane at {float(t_cross):.2f} s): "
          f"hit={out.hit} returned={out.success}")
