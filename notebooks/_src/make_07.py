# ruff: noqa: E501  (cell source lines are kept as they appear in the notebook)
"""Writes notebooks/07_anticipatory_action_selection.ipynb (run from the repository root)."""

import nbformat as nbf

md, code = nbf.v4.new_markdown_cell, nbf.v4.new_code_cell
cells = [
    md(
        "# 07 · Anticipatory action selection: when and how to start a hitting movement\n\n"
        "Thesis Ch. 4. The robot's prediction of the opponent's target improves as the opponent's "
        "stroke proceeds (notebook 04), but a hitting movement takes time: waiting gives a better "
        "prediction, starting early gives the arm time to get there. Choosing *when* to start and "
        "*which* movement is an **optimal stopping problem under partial observability**:\n\n"
        "* actions: `wait`, or stop with `forehand`, `middle` or `backhand`;\n"
        "* belief state theta_t: the online IDDM filter's latent mean and covariance plus its "
        "histogram over a grid of targets (Sec. 4.2.5);\n"
        "* reward: +1 if the movement returns the ball, -1 otherwise, simulated with the Barrett "
        "WAM in SAPIEN (notebook 05).\n\n"
        "We build the problem from simulated strokes, learn stopping values with **LSPI** "
        "(Algorithm 4.1), plan with **Monte-Carlo planning** (Algorithms 4.2-4.3) and compare with "
        "the policy-gradient baseline **NAC** and with fixed strategies. The whole Sec. 4.3 "
        "experiment (270 strokes, 10 x 10-fold cross-validation, Fig. 4.6-4.7) is "
        "`hgpdm anticipation --full`; its table is in the README."
    ),
    code(
        "import os\n"
        "import matplotlib.pyplot as plt\n"
        "import torch\n\n"
        "from hgpdm_torch.decision import (ACTIONS, MonteCarloPlanner, RadialBasis, StoppingProblem,\n"
        "                                  lspi, nac)\n"
        "from hgpdm_torch.experiments import anticipation as ant\n"
        "from hgpdm_torch.robots.table_tennis import DEFAULT_START_TIMES, make_trials, reward_table\n"
        "from hgpdm_torch.robots.table_tennis.strokes import MOVEMENTS\n\n"
        "torch.set_default_dtype(torch.float64)\n"
        "SMOKE = os.environ.get('HGPDM_SMOKE') == '1'  # CI runs this notebook with fewer strokes\n"
        "trials = make_trials(14 if SMOKE else 60, seed=3)\n"
        "# every movement started at every decision time, simulated in SAPIEN (cached on disk)\n"
        "rewards = reward_table(trials, MOVEMENTS, DEFAULT_START_TIMES, workers=2, progress=False)\n"
        "rewards = rewards.double()\n"
        "print('strokes', len(trials), 'rewards', tuple(rewards.shape),\n"
        "      'decision times [s]', DEFAULT_START_TIMES)"
    ),
    md(
        "## The reward table\n\n"
        "Success rate of each movement started at each decision time (relative to the opponent's "
        "hit). Starting late leaves the side movements too little time; starting early commits the "
        "robot before the target is known. Strokes that no movement can return at any time lie "
        "outside the robot's hitting region and are excluded, as in the thesis."
    ),
    code(
        "valid = ant.valid_trials(rewards)\n"
        "rate = (rewards[valid] > 0).double().mean(0)  # [movement, time]\n"
        "fig, ax = plt.subplots(figsize=(6, 2.6))\n"
        "im = ax.imshow(rate, vmin=0, vmax=1, cmap='viridis')\n"
        "ax.set_xticks(range(len(DEFAULT_START_TIMES)),\n"
        "              [f'{round(1000 * s)} ms' for s in DEFAULT_START_TIMES])\n"
        "ax.set_yticks(range(len(MOVEMENTS)), MOVEMENTS)\n"
        "fig.colorbar(im, label='success rate')\n"
        "ax.set_title(f'{int(valid.sum())} of {len(trials)} strokes inside the hitting region');"
    ),
    md(
        "## Beliefs from the online IDDM\n\n"
        "`fit_beliefs` fits an IDDM (continuous target) on the training strokes and runs the online "
        "filter (Algorithm 3.2) over every stroke, keeping the belief at each decision time. "
        "`StoppingProblem` pairs the belief vectors with the reward table; radial basis features "
        "with K-means centres (Eq. 37) give the linear value function."
    ),
    code(
        "idx = torch.nonzero(valid).flatten()\n"
        "perm = idx[torch.randperm(len(idx), generator=torch.Generator().manual_seed(0))]\n"
        "n_test = len(idx) // 3\n"
        "test, train = perm[:n_test].sort().values, perm[n_test:].sort().values\n"
        "config = ant.AnticipationConfig.smoke() if SMOKE else ant.AnticipationConfig(centres=40)\n"
        "steps_at = ant.decision_indices(trials.obs_times, DEFAULT_START_TIMES)\n"
        "beliefs = ant.fit_beliefs(trials.obs, trials.targets, steps_at, train, test, config)\n"
        "problem = StoppingProblem(beliefs.vectors(), rewards)\n"
        "train_p, test_p = problem.subset(train), problem.subset(test)\n"
        "basis = RadialBasis(config.centres, bias=True).fit(train_p.beliefs.flatten(0, 1))\n"
        "print('belief vector', problem.beliefs.shape[-1], 'features;', len(train), 'training and',\n"
        "      len(test), 'test strokes')"
    ),
    md(
        "## LSPI (Algorithm 4.1)\n\n"
        "Every training stroke gives one episode per (start time, movement): wait until the start "
        "time, then stop with the movement. LSPI turns them into transitions and iterates "
        "least-squares policy evaluation (ridge-regularised) and greedy improvement. Stopping "
        "actions are absorbing. Below: the learned values of one test stroke over time."
    ),
    code(
        "episodes = train_p.enumerate_episodes()\n"
        "result = lspi(train_p.transitions(episodes, unique=True), features=basis, ridge=config.ridge)\n"
        "q = result.q\n"
        "j = 0\n"
        "values = q.values(basis(test_p.beliefs[j]))  # [T, actions]\n"
        "for a, name in enumerate(ACTIONS):\n"
        "    plt.plot([round(1000 * s) for s in DEFAULT_START_TIMES], values[:, a], 'o-', label=name)\n"
        "plt.xlabel('decision time relative to the opponent\\'s hit [ms]'); plt.ylabel('Q')\n"
        "plt.title(f'test stroke {int(test[j])}, target {float(trials.targets[test[j]]):+.2f} m')\n"
        "plt.legend();"
    ),
    md(
        "## Monte-Carlo planning (Algorithms 4.2-4.3)\n\n"
        "Instead of trusting the learned value of waiting, MCP projects the belief one step ahead: "
        "it samples the next observation from the IDDM's predictive distribution, updates the "
        "belief of every particle in one batched filter step, and values each with LSPI's stopping "
        "values. Sampling stops early once a Student-t confidence interval separates waiting from "
        "the best stop."
    ),
    code(
        "planner = MonteCarloPlanner(beliefs.model, beliefs.belief_filter, q, basis,\n"
        "                            num_particles=config.particles, confidence=config.confidence)\n"
        "gen = torch.Generator().manual_seed(0)\n"
        "for t in range(test_p.horizon - 1):  # the robot's decisions during test stroke j\n"
        "    d = planner.decide(beliefs.belief(int(test[j]), t), generator=gen)\n"
        "    print(f'{round(1000 * DEFAULT_START_TIMES[t]):5d} ms: stop values',\n"
        "          [round(v, 2) for v in d.q_stop.tolist()],\n"
        "          f'wait {d.q_wait:+.2f} from {d.particles} particles ->', ACTIONS[d.action])\n"
        "    if d.action:  # a movement was started: the episode ends\n"
        "        break"
    ),
    md(
        "## NAC: the policy-gradient baseline\n\n"
        "The episodic natural actor-critic learns a softmax policy over the same features from "
        "sampled episodes. Its return climbs from the uniform policy's."
    ),
    code(
        "nac_result = nac(train_p, basis(train_p.beliefs), iterations=config.nac_iterations,\n"
        "                 episodes_per_trial=config.nac_episodes, step_size=config.nac_step,\n"
        "                 generator=torch.Generator().manual_seed(0))\n"
        "plt.plot(nac_result.returns); plt.xlabel('NAC update'); plt.ylabel('mean return');"
    ),
    md(
        "## Test strokes\n\n"
        "Successful returns on the held-out strokes: each single movement started 240 ms before the "
        "hit, LSPI's greedy policy, MCP and NAC (expected successes of the stochastic policy). "
        "With this few strokes the numbers are noisy; `hgpdm anticipation --full` gives the "
        "cross-validated comparison."
    ),
    code(
        "single = DEFAULT_START_TIMES.index(-0.24)\n"
        "rows = {f'always {m} @240ms': int((test_p.rewards[:, a, single] > 0).sum())\n"
        "        for a, m in enumerate(MOVEMENTS)}\n"
        "rows['LSPI'] = ant.successes(test_p.run(ant.greedy_policy(q, basis, test_p)))\n"
        "rows['MCP'] = ant.successes(test_p.run(ant.mcp_policy(planner, beliefs, test,\n"
        "                                                      test_p.horizon, gen)))\n"
        "allowed = torch.stack([test_p.allowed(t) for t in range(test_p.horizon)])\n"
        "probs = nac_result.policy.probs(basis(test_p.beliefs), allowed)\n"
        "rows['NAC'] = float(((1 + test_p.expected_reward(probs)) / 2).sum())\n"
        "for name, won in rows.items():\n"
        "    print(f'{name:24s} {won:5.1f} / {len(test)}')"
    ),
]

nb = nbf.v4.new_notebook()
nb["cells"] = cells
nb["metadata"]["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
nbf.write(nb, "notebooks/07_anticipatory_action_selection.ipynb")
