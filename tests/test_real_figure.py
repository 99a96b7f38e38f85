"""``scripts/real_figure.py`` (the README's real-flight figure): the window it shows is the one that climbs or descends
the most while it turns, on tracks whose climb and turn are known in closed form, and it writes the figure."""

import runpy

import numpy as np
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.config import REPO_ROOT

SCRIPT = REPO_ROOT / "scripts" / "real_figure.py"


def _tracks(T: int = 60) -> np.ndarray:
    """``[4, T, 9]`` states at 1 s: level and straight; climbing 5 m/s straight (300 m, no turn); a level half
    circle (pi rad, no climb); a quarter circle climbing 3 m/s (180 m x pi/2 rad, the largest product)."""
    t = np.arange(T, dtype=np.float64)
    v = 100.0
    states = np.zeros((4, T, 9))
    for i, (rate, climb) in enumerate([(0.0, 0.0), (0.0, 5.0), (np.pi / (T - 1), 0.0), (np.pi / 2 / (T - 1), 3.0)]):
        heading = rate * t
        vx, vy = v * np.cos(heading), v * np.sin(heading)
        x = np.cumsum(vx) - vx[0]
        y = np.cumsum(vy) - vy[0]
        states[i, :, 0], states[i, :, 1], states[i, :, 3], states[i, :, 4] = x, vx, y, vy
        states[i, :, 6], states[i, :, 7] = 1000.0 + climb * t, climb
    return states


def test_the_window_shown_climbs_the_most_while_it_turns():
    states = _tracks()
    batch = TensorDict({keys.STATES: torch.from_numpy(states)}, batch_size=[4])
    pick = runpy.run_path(str(SCRIPT))["pick_window"]
    assert pick(batch) == 3  # 180 m x pi/2 against 300 m x 0 and 0 x pi
    assert pick(batch[[0, 1, 2, 3, 3]][[4, 1, 2, 0]]) == 0  # the same window wherever it lies


def test_it_writes_the_figure_of_the_picked_window(tmp_path, capsys):
    states = _tracks()
    rng = np.random.default_rng(0)
    z = states[..., [0, 3, 6]] + 4.0 * rng.standard_normal((4, states.shape[1], 3))
    data = tmp_path / "set.npz"
    np.savez(data, states=states.astype(np.float32), measurements=z.astype(np.float32), dt=1.0,
             r=np.full(4, 4.0, np.float32))
    main = runpy.run_path(str(SCRIPT))["main"]
    out = tmp_path / "fig.png"
    assert main(["--data", str(data), "--methods", "measurements,real-imm-singer", "--out", str(out)]) == 0
    assert "(window 3)" in capsys.readouterr().out
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
