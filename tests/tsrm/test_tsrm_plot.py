"""Episode picture: stages of the frames, the searched region drawn, a PNG written."""

import numpy as np
import pytest
from PIL import Image

from tsnav.constants import CATEGORY_INDEX, NUM_CATEGORIES
from tsnav.data.toy import toy_scene
from tsnav.tsrm.area import ExactSearchedRegion
from tsnav.tsrm.plot import draw_episode, episode_stages, searched_region

BOWL = CATEGORY_INDEX["Bowl"]


def test_episode_stages():
    conf = np.zeros((10, NUM_CATEGORIES))
    conf[[4, 6], BOWL] = 0.9
    st = episode_stages([1, 2, 4, 3, 6], BOWL, conf)
    assert st.switch_frame == 2 and st.searching_frames.tolist() == [0, 1, 2]
    st = episode_stages([4, 2], BOWL, conf)  # the start frame counts
    assert st.switch_frame == 0 and len(st.searching_frames) == 0
    st = episode_stages([1, 2], BOWL, conf)
    assert st.switch_frame == -1 and st.searching_frames.tolist() == [0, 1]


def test_searched_region_equals_incremental_reference():
    sc = toy_scene(4.0, 3.0)
    rng = np.random.default_rng(0)
    s = [int(rng.integers(sc.num_states))]
    for _ in range(15):
        s.append(int(sc.next_state[s[-1], rng.integers(5)]))
    ref = ExactSearchedRegion(sc.floor)
    for t in s:
        ref.add(sc.x[t], sc.z[t], sc.rotation[t], sc.horizon[t])
    assert searched_region(sc, s).area == pytest.approx(ref.area, rel=1e-9)


def test_draw_episode_writes_png(tmp_path):
    sc = toy_scene(4.0, 3.0, objects={"Bowl|1": (4.0, 3.0)})
    sc.meta["furniture"] = [{"category": "Table", "footprint": [[1.6, 0.9], [2.4, 0.9], [2.4, 1.4], [1.6, 1.4]]}]
    s = sc.index("0.00|1.50|180|0")
    states = [s]
    for a in [2, 2, 0, 0, 2, 2, 0, 0, 0, 2, 2, 0, 0, 1, 0, 0]:
        states.append(int(sc.next_state[states[-1], a]))
    out = draw_episode(sc, states, "Bowl", tmp_path / "ep" / "episode.png")
    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape[0] > 300 and img.shape[1] > 300
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 10  # more than a blank canvas
    with pytest.raises(ValueError, match="state ids"):
        draw_episode(sc, [10**6], "Bowl", tmp_path / "bad.png")
