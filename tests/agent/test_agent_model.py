"""Policy network (paper III-D): target memory (FIFO writes, order invariance, empty memory), relative poses,
hidden-state reset on done, RoI pooling, oracle detection table and observations on the tiny world."""

import math

import numpy as np
import pytest
import torch

from tsnav.agent import (
    NO_ACTION,
    ActorCritic,
    AgentObs,
    AgentState,
    DetectionTable,
    MemoryState,
    Observer,
    TargetMemoryAggregator,
    agent_config,
    relative_pose,
    roi_pool,
)
from tsnav.agent.model import BLOCKED_MOVE
from tsnav.detect.oracle import oracle_detections
from tsnav.sim.batch import SceneBank

D = 6


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _filled_memory(b=3, m=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    mem = MemoryState.empty(b, m, D)
    for _ in range(4):
        mask = torch.rand(b, generator=g) < 0.8
        mem = mem.write(
            mask,
            torch.rand(b, 4, generator=g),
            torch.rand(b, generator=g),
            torch.randn(b, D, generator=g),
            torch.randn(b, 4, generator=g) * 30,
        )
    return mem


def test_memory_fifo_write_and_clear():
    b, m = 2, 3
    mem = MemoryState.empty(b, m, D)
    mask = torch.tensor([True, False])
    for k in range(m + 2):  # five writes into three slots: nodes 2, 3, 4 remain in row 0
        mem = mem.write(
            mask,
            torch.full((b, 4), float(k)),
            torch.full((b,), float(k)),
            torch.full((b, D), float(k)),
            torch.full((b, 4), float(k)),
        )
    assert mem.valid[0].all() and not mem.valid[1].any()
    assert sorted(mem.score[0].tolist()) == [2.0, 3.0, 4.0]
    assert int(mem.ptr[0]) == (m + 2) % m and int(mem.ptr[1]) == 0
    cleared = mem.clear(torch.tensor([True, False]))
    assert not cleared.valid.any() and int(cleared.ptr[0]) == 0
    assert mem.valid[0].all()  # functional: the old state is untouched


def test_aggregator_shapes_and_order_invariance():
    torch.manual_seed(0)
    agg = TargetMemoryAggregator(D, dim=16, heads=2, out_dim=12).eval()
    mem = _filled_memory()
    pose = torch.tensor([[0.5, 1.0, 90.0, 0.0], [0.0, 0.0, 0.0, 30.0], [1.0, -1.0, 315.0, 0.0]])
    target = torch.tensor([1, 4, 21])
    out = agg(mem, pose, target)
    assert out.shape == (3, 12) and torch.isfinite(out).all()
    perm = torch.tensor([3, 0, 4, 2, 1])
    permuted = MemoryState(
        mem.box[:, perm], mem.score[:, perm], mem.feat[:, perm], mem.pose[:, perm], mem.valid[:, perm], mem.ptr
    )
    torch.testing.assert_close(agg(permuted, pose, target), out, rtol=1e-5, atol=1e-6)
    # the content of empty slots does not matter
    junk = MemoryState(
        torch.where(mem.valid[..., None], mem.box, torch.full_like(mem.box, 7.0)),
        mem.score,
        torch.where(mem.valid[..., None], mem.feat, torch.full_like(mem.feat, -9.0)),
        mem.pose,
        mem.valid,
        mem.ptr,
    )
    torch.testing.assert_close(agg(junk, pose, target), out, rtol=1e-5, atol=1e-6)


def test_empty_memory_gives_the_nothing_vector():
    torch.manual_seed(0)
    agg = TargetMemoryAggregator(D, dim=16, heads=2, out_dim=12).eval()
    with torch.no_grad():
        agg.nothing.normal_()
    empty = _filled_memory(seed=1).clear(torch.ones(3, dtype=torch.bool))  # garbage in every slot, none valid
    pose = torch.zeros(3, 4)
    target = torch.tensor([2, 2, 5])
    out = agg(empty, pose, target)
    assert torch.isfinite(out).all()
    q = agg.query(target)
    want = torch.relu(agg.out(torch.cat([agg.nothing.expand_as(q), q], dim=1)))
    torch.testing.assert_close(out, want)
    # gradients flow to the nothing vector and stay finite
    out.sum().backward()
    assert agg.nothing.grad is not None and torch.isfinite(agg.nothing.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in agg.parameters() if p.grad is not None)


def test_relative_pose_by_hand():
    node = torch.tensor([[[1.0, 0.0, 90.0, 30.0], [0.0, 2.0, 0.0, 0.0]]])
    facing_x = relative_pose(node, torch.tensor([[0.0, 0.0, 90.0, 0.0]]))
    # facing +x: a node 1 m along +x is 1 m ahead; one 2 m along +z is 2 m to the left
    np.testing.assert_allclose(facing_x[0, 0, :2], [1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(facing_x[0, 1, :2], [0.0, -2.0], atol=1e-6)
    np.testing.assert_allclose(facing_x[0, 0, 2:], [0.0, 1.0, 1.0], atol=1e-6)  # same yaw, horizon 30
    facing_z = relative_pose(node, torch.tensor([[0.0, 0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(facing_z[0, 0, :2], [0.0, 1.0], atol=1e-6)  # +x is to the right of +z
    np.testing.assert_allclose(facing_z[0, 0, 2:4], [1.0, 0.0], atol=1e-6)  # node yaw 90 = current + 90
    assert math.isclose(float(facing_z[0, 1, 0]), 2.0, abs_tol=1e-6)


def _obs(b, c=8, h=2, w=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    score = (torch.rand(b, generator=g) > 0.4).float()
    return AgentObs(
        image=torch.randn(b, c, h, w, generator=g),
        target=torch.randint(0, 22, (b,), generator=g),
        det_score=score,
        det_box=torch.rand(b, 4, generator=g) * score[:, None],
        det_feat=torch.randn(b, c, generator=g),
        pose=torch.randn(b, 4, generator=g),
    )


def test_hidden_state_reset_on_done():
    torch.manual_seed(0)
    model = ActorCritic(agent_config("cpu", memory_slots=4), (8, 2, 2), det_dim=8).eval()
    b = 4
    state = model.initial_state(b)
    for t in range(3):
        _, _, state = model(_obs(b, seed=t), state)
        state = state.with_action(torch.tensor([0, 1, 2, 3]))
    assert state.h.abs().sum(1).min() > 0 and state.memory.valid.any(1).all()
    done = np.array([True, False, True, False])
    reset = state.reset(done)
    assert (reset.h[[0, 2]] == 0).all() and (reset.c[[0, 2]] == 0).all()
    torch.testing.assert_close(reset.h[[1, 3]], state.h[[1, 3]])
    assert reset.prev_action.tolist() == [NO_ACTION, 1, NO_ACTION, 3]
    assert not reset.memory.valid[[0, 2]].any() and (reset.memory.valid[[1, 3]] == state.memory.valid[[1, 3]]).all()
    # a reset row behaves exactly like a fresh episode
    obs = _obs(b, seed=9)
    with torch.no_grad():
        la, va, _ = model(obs, reset)
        lb, vb, _ = model(obs, model.initial_state(b))
    torch.testing.assert_close(la[[0, 2]], lb[[0, 2]])
    torch.testing.assert_close(va[[0, 2]], vb[[0, 2]])
    assert not torch.allclose(la[[1, 3]], lb[[1, 3]])


def test_model_shapes_init_and_dropout():
    torch.manual_seed(0)
    model = ActorCritic(agent_config("cpu"), (8, 2, 2), det_dim=8)
    logits, value, state = model(_obs(5), model.initial_state(5))
    assert logits.shape == (5, 6) and value.shape == (5,)
    assert logits.abs().max() < 0.5  # actor gain 0.01: near-uniform policy at the start
    w = model.state.weight.detach()
    q = w @ w.T if w.shape[0] <= w.shape[1] else w.T @ w
    torch.testing.assert_close(q / q.diagonal().mean(), torch.eye(q.shape[0]), atol=1e-4, rtol=0)
    assert model.dropout.p == 0.45 and agent_config().dropout == 0.45
    with pytest.raises(ValueError, match="dropout"):
        agent_config("cpu", dropout=1.5)


def test_blocked_move_has_its_own_previous_action_id():
    """AgentConfig.blocked_action (a deviation, off by default): a MoveAhead after which the position (x, z) is the
    one it was taken from is BLOCKED_MOVE; a MoveAhead that moved, a rotation in place, an episode start and rows
    of a reset keep their ids; the flag off leaves the paper's input (and its embedding size) as it was."""
    torch.manual_seed(0)
    plain = ActorCritic(agent_config("cpu"), (8, 2, 2), det_dim=8)
    model = ActorCritic(agent_config("cpu", blocked_action=True), (8, 2, 2), det_dim=8).eval()
    assert plain.action_embed.num_embeddings == NO_ACTION + 1 and model.action_embed.num_embeddings == NO_ACTION + 2
    assert plain.initial_state(2).prev_position is None
    b = 5
    obs = _obs(b, seed=1)
    state = model.initial_state(b)
    assert model.previous_action_ids(obs, state).tolist() == [NO_ACTION] * b  # nothing blocked at a start
    with torch.no_grad():
        _, _, state = model(obs, state)
    torch.testing.assert_close(state.prev_position, obs.pose[:, :2])
    state = state.with_action(torch.tensor([0, 0, 1, 0, 0]))  # MoveAhead, MoveAhead, RotateLeft, MoveAhead x2
    nxt = _obs(b, seed=2)
    pose = obs.pose.clone()
    pose[1, 0] += 0.25  # row 1 moved along x
    pose[3, 1] -= 0.25  # row 3 moved along z
    pose[:, 2] += 45.0  # headings do not matter
    nxt.pose = pose
    state = state.reset(np.array([False, False, False, False, True]))  # row 4 starts a new episode
    assert model.previous_action_ids(nxt, state).tolist() == [BLOCKED_MOVE, 0, 1, 0, NO_ACTION]
    # the reference: one row at a time, by the rule's words
    want = [
        BLOCKED_MOVE
        if int(state.prev_action[i]) == 0 and bool((nxt.pose[i, :2] == state.prev_position[i]).all())
        else int(state.prev_action[i])
        for i in range(b)
    ]
    assert model.previous_action_ids(nxt, state).tolist() == want
    # the id reaches the network: the blocked row differs from the same row taken as moved, the others do not
    moved = AgentState(state.h, state.c, state.memory, state.prev_action, state.prev_position + 1.0)
    with torch.no_grad():
        la, _, _ = model(nxt, state)
        lc, _, _ = model(nxt, moved)
    assert not torch.allclose(la[0], lc[0]) and torch.allclose(la[1:], lc[1:])
    assert plain.previous_action_ids(nxt, plain.initial_state(b)).tolist() == [NO_ACTION] * b
    with pytest.raises(ValueError, match="previous position"):
        model.previous_action_ids(nxt, AgentState(state.h, state.c, state.memory, state.prev_action))


def test_roi_pool():
    img = torch.arange(2 * 3 * 4 * 4, dtype=torch.float32).reshape(2, 3, 4, 4)
    box = torch.tensor([[0.0, 0.0, 1.0, 1.0], [0.25, 0.5, 0.5, 0.75]])
    out = roi_pool(img, box)
    torch.testing.assert_close(out[0], img[0].mean(dim=(1, 2)))
    torch.testing.assert_close(out[1], img[1, :, 2, 1])  # row 2 (y 0.5-0.75), column 1 (x 0.25-0.5)
    assert (roi_pool(img, torch.zeros(2, 4)) == 0).all()


def test_oracle_detections_and_observer(tiny_scenes):
    """The table installed in the bank (here the oracle's, rows in pixels) becomes scores and boxes as
    fractions of the image side; nothing detected -> zero box."""
    bank = SceneBank(tiny_scenes)
    bank.set_detections(np.concatenate([oracle_detections(s).rows() for s in tiny_scenes]))
    det = DetectionTable(bank)
    assert det.source == "detector"
    np.testing.assert_array_equal(det.score, bank.detections[..., 0])
    boxes = det.box
    seen = bank.in_frame  # the oracle reports exactly the instances in frame
    np.testing.assert_array_equal(det.score > 0, seen)
    assert (boxes[~seen] == 0).all()
    b = boxes[seen]
    assert (b >= 0).all() and (b <= 1).all() and (b[:, 2] >= b[:, 0]).all() and (b[:, 3] >= b[:, 1]).all()
    feats = torch.randn(bank.num_states, 4, 2, 2).half()
    obs_fn = Observer(bank, feats)
    s, g = np.nonzero(seen)
    rows = np.array([0, len(s) // 2, len(s) - 1])
    obs = obs_fn(s[rows], g[rows])
    assert obs.image.shape == (3, 4, 2, 2) and obs.det_feat.shape == (3, 4)
    assert (obs.det_score > 0).all() and obs.image.dtype == torch.float32
    np.testing.assert_allclose(obs.pose[:, 0].numpy(), bank.x[s[rows]])
    with pytest.raises(ValueError, match="features cover"):
        Observer(bank, feats[:-1])


@pytest.mark.parametrize("dim,heads", [(64, 2), (256, 4)])
def test_memory_attention_fast_path_equals_multihead_attention(dim, heads):
    """``TargetMemoryAggregator.attend`` (key and value projections moved to the query side) computes the same
    outputs and gradients as ``nn.MultiheadAttention``'s forward (``attend_reference``), padded slots included."""
    torch.manual_seed(0)
    agg = TargetMemoryAggregator(feat_dim=8, dim=dim, heads=heads, out_dim=32)
    with torch.no_grad():  # non-zero biases, so that the bias algebra is exercised
        agg.attn.in_proj_bias.normal_()
        agg.attn.out_proj.bias.normal_()
    b, m = 37, 8
    q = torch.randn(b, dim, dtype=torch.float64, requires_grad=True)
    nodes = torch.randn(b, m, dim, dtype=torch.float64, requires_grad=True)
    pad = torch.rand(b, m) < 0.5
    pad[:, 0] = False  # the aggregator never pads every slot of a row
    pad[3] = True
    pad[3, 5] = False
    agg = agg.double()
    outs, grads = [], []
    for fn in (agg.attend, agg.attend_reference):
        agg.zero_grad()
        q.grad = nodes.grad = None
        out = fn(q, nodes, pad)
        (out * torch.linspace(-1, 1, dim, dtype=torch.float64)).sum().backward()
        outs.append(out.detach())
        grads.append([q.grad.clone(), nodes.grad.clone()] + [p.grad.clone() for p in agg.attn.parameters()])
    assert torch.allclose(outs[0], outs[1], atol=1e-10)
    for g0, g1 in zip(*grads):
        assert torch.allclose(g0, g1, atol=1e-10)


@pytest.mark.parametrize("dim,heads,dtype", [(64, 2, torch.float32), (256, 4, torch.float32), (64, 2, torch.bfloat16)])
def test_memory_attention_products_are_einsums_bit_for_bit(dim, heads, dtype):
    """``attend``'s batched matrix products against the einsums they stand for (``attend_einsum``): the same
    output and gradients of the queries, the nodes and every attention weight, bit for bit (bf16: under autocast,
    as the trainer's bf16 rollouts run)."""
    torch.manual_seed(1)
    agg = TargetMemoryAggregator(feat_dim=8, dim=dim, heads=heads, out_dim=32)
    with torch.no_grad():
        agg.attn.in_proj_bias.normal_()
    b, m = 29, 8
    q0, n0 = torch.randn(b, dim), torch.relu(torch.randn(b, m, dim))
    pad = torch.rand(b, m) < 0.5
    pad[:, 0] = False
    res = []
    for fn in (agg.attend, agg.attend_einsum):
        agg.zero_grad()
        q, nodes = (q0 * 1.0).requires_grad_(), (n0 * 1.0).requires_grad_()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=dtype == torch.bfloat16):
            out = fn(q * 2.0, nodes * 1.0, pad)  # non-leaf inputs, as in the network
        (out.float() * torch.linspace(-1, 1, dim)).sum().backward()
        res.append([out.detach(), q.grad, nodes.grad] + [p.grad.clone() for p in agg.attn.parameters()])
    assert res[0][0].dtype == dtype
    for x, y in zip(*res):
        assert torch.equal(x, y)


def test_memory_history_keeps_every_steps_box_and_score():
    """AgentConfig.memory_history (issue 47, a deviation, off by default): off, the network has the parameters, the
    description and the recurrent state it had before the setting (shipped agents load and act as before); on,
    ``memory.history.*`` is added after the others (the shared parameters are initialised as without it), the
    history holds the box and score of each of the last ``memory_slots`` steps whatever the score (ages 0 = newest),
    it is emptied on done, and an old step's box reaches the output."""
    torch.manual_seed(0)
    plain = ActorCritic(agent_config("cpu", memory_slots=3), (8, 2, 2), det_dim=8).eval()
    torch.manual_seed(0)
    model = ActorCritic(agent_config("cpu", memory_slots=3, memory_history=True), (8, 2, 2), det_dim=8).eval()
    names = dict(plain.named_parameters())
    extra = {k: v.shape for k, v in model.named_parameters() if k not in names}
    assert extra == {"memory.history.weight": (64, 11), "memory.history.bias": (64,)}
    assert not any("history" in k for k in names) and "memory_history" not in plain.describe()["agent"]
    assert model.describe()["agent"]["memory_history"] is True
    for k, v in names.items():  # initialised as without the history
        assert torch.equal(v, dict(model.named_parameters())[k]), k
    assert plain.initial_state(2).history is None
    again = ActorCritic.from_description(model.describe())
    assert again.config.memory_history and "memory.history.weight" in again.state_dict()
    assert "memory.history.weight" in model.autocast_weights()

    b = 4
    state = model.initial_state(b)
    seen = []
    with torch.no_grad():
        for t in range(5):
            obs = _obs(b, seed=t)
            seen.append(obs)
            _, _, state = model(obs, state)
            state = state.with_action(torch.zeros(b, dtype=torch.long))
    hist = state.history
    assert hist.valid.all() and hist.feat.shape == (b, 3, 0)
    from tsnav.agent.memory import slot_age

    age = slot_age(hist)
    for row in range(b):  # the slot of age a holds the step 4 - a: the last three steps, scores 0 included
        for slot in range(3):
            step = 4 - int(age[row, slot])
            assert torch.equal(hist.box[row, slot], seen[step].det_box[row])
            assert hist.score[row, slot] == seen[step].det_score[row]
            assert torch.equal(hist.pose[row, slot], seen[step].pose[row])
    assert sorted(age[0].tolist()) == [0, 1, 2]
    # the box of the oldest step kept after the next write (age 1 now) reaches F_t, and so the policy
    obs = _obs(b, seed=9)
    with torch.no_grad():
        la, _, _ = model(obs, state)
        oldest = (age == 1).nonzero()[0]
        box = hist.box.clone()
        box[oldest[0], oldest[1]] = torch.tensor([0.0, 0.0, 1.0, 1.0])
        changed = MemoryState(box, hist.score, hist.feat, hist.pose, hist.valid, hist.ptr)
        lb, _, _ = model(obs, AgentState(state.h, state.c, state.memory, state.prev_action, None, changed))
    assert not torch.equal(la[oldest[0]], lb[oldest[0]])
    rest = [r for r in range(b) if r != int(oldest[0])]
    assert torch.equal(la[rest], lb[rest])
    cleared = state.reset(np.array([True, False, False, False]))
    assert not cleared.history.valid[0].any() and cleared.history.valid[1:].all()
    assert cleared.index(torch.tensor([1, 2])).history.box.shape == (2, 3, 4)
    with pytest.raises(ValueError, match="history"):
        model.memory(state.memory, obs.pose, obs.target)


def test_box_depth_stats_match_their_reference():
    from tsnav.agent.observe import FAR, box_depth_stats, box_depth_stats_reference

    rng = np.random.default_rng(0)
    maps = torch.from_numpy(rng.uniform(0.2, 7.0, (300, 32, 32)).astype(np.float32))
    corners = np.sort(rng.random((300, 2, 2)), axis=1)
    box = torch.from_numpy(corners.transpose(0, 2, 1).reshape(300, 4)[:, [0, 2, 1, 3]].astype(np.float32))
    score = torch.from_numpy(np.where(rng.random(300) < 0.2, 0.0, rng.random(300)).astype(np.float32))
    fast = box_depth_stats(maps, box, score).numpy()
    assert np.allclose(fast, box_depth_stats_reference(maps, box, score), atol=1e-6)
    # by hand: a box 3 cells wide (x) and 1 high (y) over row 0: 1, 2, 3 m (median 2, minimum 1, p10 1); the
    # cells below them (row 1) hold 0.5 m and stay outside, as do those right of them
    m = torch.full((1, 32, 32), 9.0)
    m[0, 0, :3] = torch.tensor([1.0, 2.0, 3.0])
    m[0, 1, :3] = 0.5
    out = box_depth_stats(m, torch.tensor([[0.0, 0.0, 3 / 32, 1 / 32]]), torch.tensor([0.9]))
    assert out[0].tolist() == pytest.approx([2 / FAR, 1 / FAR, 1 / FAR, 1.0])
    nothing = box_depth_stats(m, torch.zeros(1, 4), torch.zeros(1))
    assert nothing[0].tolist() == [1.0, 1.0, 1.0, 0.0]


def test_target_depth_is_added_last_and_reaches_the_output():
    """AgentConfig.target_depth (issue 47, a deviation, off by default): ``depth_in.*`` is made after the other
    parameters (initialised as without it), the description names it, a network without it describes itself as
    before, and the depth input changes the output; an observation without it is refused in one line."""
    torch.manual_seed(0)
    plain = ActorCritic(agent_config("cpu"), (8, 2, 2), det_dim=8).eval()
    torch.manual_seed(0)
    model = ActorCritic(agent_config("cpu", target_depth="r.safetensors"), (8, 2, 2), det_dim=8).eval()
    names = dict(plain.named_parameters())
    extra = {k: v.shape for k, v in model.named_parameters() if k not in names}
    assert extra == {"depth_in.weight": (128, 4), "depth_in.bias": (128,)}
    for k, v in names.items():
        assert torch.equal(v, dict(model.named_parameters())[k]), k
    assert "target_depth" not in plain.describe()["agent"]
    assert ActorCritic.from_description(model.describe()).config.target_depth == "r.safetensors"
    assert "depth_in.weight" in model.autocast_weights()
    obs = _obs(3)
    with pytest.raises(ValueError, match="needs a TargetDepth"):
        model(obs, model.initial_state(3))
    near, far = [], []
    for d, out in ((0.1, near), (1.0, far)):
        o = _obs(3)
        o.det_depth = torch.tensor([[d, d, d, 1.0]] * 3)
        with torch.no_grad():
            out.append(model(o, model.initial_state(3))[0])
    assert not torch.allclose(near[0], far[0])
