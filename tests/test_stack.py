"""The non-destructive tool stack: same result as applying entries one by one, cached tail."""

import numpy as np
import pytest

from volumeevm_addon import EVM, VolumeEVM
from volumeevm_addon.model import EditStack, ToolOperation, box_evm


@pytest.fixture(scope="module")
def head(data_dir):
    return np.load(data_dir / "ct_head_invesalius.npy")


@pytest.fixture(scope="module")
def tools(head):
    x, y, z = np.ogrid[: head.shape[0], : head.shape[1], : head.shape[2]]
    drill = EVM.from_mask((x - 128) ** 2 + (y - 60) ** 2 + 0 * z < 15 ** 2)
    box = np.zeros(head.shape, bool)
    box[40:220, 40:220, 10:100] = True
    implant = np.zeros(head.shape, bool)
    implant[120:136, 50:70, 40:60] = True
    return drill, EVM.from_mask(box), EVM.from_mask(implant)


def test_stack_equals_entries_applied_one_by_one_and_disabling_restores(head, tools):
    drill, box, implant = tools
    base = VolumeEVM.from_array(head, 300)
    operations = [ToolOperation(box, "keep"), ToolOperation(drill, "cut"),
                  ToolOperation(implant, "add", density=3000)]
    stack = EditStack(base)
    result = stack.evaluate(operations)
    expected = base.keep(box).cut(drill).add(implant, 3000)
    assert result.evm == expected.evm
    assert np.array_equal(result.table(0), expected.table(0))
    assert stack.last_recomputed == 3

    disabled = [operations[0], ToolOperation(drill, "cut", enabled=False), operations[2]]
    again = stack.evaluate(disabled)
    assert stack.last_recomputed == 2
    without = base.keep(box).add(implant, 3000)
    assert again.evm == without.evm and np.array_equal(again.table(0), without.table(0))

    restored = stack.evaluate(operations)
    assert restored.evm == result.evm and np.array_equal(restored.table(0), result.table(0))


def test_moving_the_last_tool_recomputes_only_it(head, tools):
    drill, box, implant = tools
    stack = EditStack(VolumeEVM.from_array(head, 300))
    operations = [ToolOperation(box, "keep"), ToolOperation(implant, "add"),
                  ToolOperation(drill, "cut")]
    stack.evaluate(operations)
    moved = ToolOperation(drill.translate(np.array([5, 0, 0])), "cut")
    result = stack.evaluate(operations[:2] + [moved])
    assert stack.last_recomputed == 1
    mask = head >= 300
    assert result.evm == ((EVM.from_mask(mask) & box) | implant) - moved.tool


def test_largest_part_entry(head, tools):
    drill, box, _ = tools
    base = VolumeEVM.from_array(head, 300)
    result = EditStack(base).evaluate([ToolOperation(drill, "cut"),
                                       ToolOperation(operation="largest")])
    expected = base.cut(drill).largest_component()
    assert result.evm == expected.evm and np.array_equal(result.table(0), expected.table(0))


def test_bad_entries():
    with pytest.raises(ValueError, match="operation must be one of"):
        ToolOperation(EVM(), "drill")
    with pytest.raises(ValueError, match="'largest' takes no tool"):
        ToolOperation(EVM(), "largest")
    with pytest.raises(ValueError, match="'cut' needs a tool"):
        ToolOperation(None, "cut")
    with pytest.raises(TypeError, match="tool must be an EVM"):
        ToolOperation(np.zeros((2, 2, 2), bool), "cut")


# ---------------------------------------------------------------------------- in place
def _ball(shape, centre, radius):
    x, y, z = np.ogrid[: shape[0], : shape[1], : shape[2]]
    c = np.asarray(centre, float)
    return EVM.from_mask((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < radius ** 2)


def _full(base, operations):
    """A fresh stack's evaluation: every entry in full; the error text if it fails."""
    try:
        return EditStack(base).evaluate(operations)
    except ValueError as error:
        return str(error)


def test_updates_in_place_equal_full_evaluations_on_random_moves(head):
    """Random drags (one tool, or two at once), toggles and density changes on a 5-entry stack
    of the CT head crop: after every step the stack's result is a fresh full evaluation's,
    region and densities, or the same error; most steps update entries in place."""
    volume = np.ascontiguousarray(head[64:192, 48:176, 30:80])
    base = VolumeEVM.from_array(volume, 300)
    shape = base.shape
    rng = np.random.default_rng(11)
    centres = [np.array([30.0, 40, 20]), np.array([64.0, 64, 25]), np.array([90.0, 30, 30]),
               np.array([50.0, 100, 12])]
    radii = [9.0, 7.0, 8.0, 6.0]
    kinds = [("cut", None), ("add", None), ("keep", None), ("add", 2000.0)]
    clip = box_evm((4, 4, 2), (124, 124, 48), shape)

    def operations(enabled):
        tools = [_ball(shape, c, r) for c, r in zip(centres, radii)]
        ops = [ToolOperation(clip, "keep")]
        for tool, (kind, density), on in zip(tools, kinds, enabled):
            if kind == "keep":  # keep a ball's surroundings: the ball's box grown by 36
                lo, hi = tool.bounds()
                tool = box_evm(np.subtract(lo, 36), np.add(hi, 36), shape)
            ops.append(ToolOperation(tool, kind, enabled=on, density=density))
        return ops

    enabled = [True, True, True, True]
    stack = EditStack(base)
    stack.evaluate(operations(enabled))
    updated = 0
    for step in range(40):
        moved = rng.choice(4, size=2 if step % 5 == 4 else 1, replace=False)
        for m in moved:  # along one axis every other step, along all three otherwise
            centres[m] = centres[m] + rng.integers(-3, 4, size=3) * (step % 2
                                                                     or np.eye(3)[step % 3])
        if step % 9 == 8:
            enabled[rng.integers(4)] ^= True
        ops = operations(enabled)
        expected = _full(base, ops)
        try:
            result = stack.evaluate(ops)
        except ValueError as error:
            assert str(error) == expected
            continue
        assert not isinstance(expected, str), expected
        assert result.evm == expected.evm
        np.testing.assert_array_equal(result.table(0), expected.table(0))
        assert result.table(0).dtype == expected.table(0).dtype
        updated += stack.last_updated
    assert updated >= 25


def test_a_tool_moved_far_or_a_changed_entry_evaluates_in_full(head):
    base = VolumeEVM.from_array(np.ascontiguousarray(head[64:192, 48:176, 30:80]), 300)
    shape = base.shape
    drill = ToolOperation(_ball(shape, (40, 40, 20), 8), "cut")
    implant = ToolOperation(_ball(shape, (60, 60, 25), 6), "add", density=1000.0)
    stack = EditStack(base)
    stack.evaluate([drill, implant])
    near = ToolOperation(_ball(shape, (42, 40, 20), 8), "cut")
    stack.evaluate([near, implant])
    assert (stack.last_recomputed, stack.last_updated) == (2, 2)
    # A keep box moved across the grid: its dirty blocks are most of it.
    box = box_evm((0, 0, 0), (100, 120, 50), shape)
    stack.evaluate([ToolOperation(box, "keep"), implant])
    stack.evaluate([ToolOperation(box.translate((10, 0, 0)), "keep"), implant])
    assert (stack.last_recomputed, stack.last_updated) == (2, 0)
    # Another operation in the first entry: it and the entries after it in full.
    stack.evaluate([ToolOperation(box, "cut"), implant])
    assert (stack.last_recomputed, stack.last_updated) == (2, 0)
    for offset in ((1, 0, 0), (1, -1, 0)):  # the box's faces across x, then across y as well
        moved = ToolOperation(box.translate(offset), "cut")
        result = stack.evaluate([moved, implant])
        assert (stack.last_recomputed, stack.last_updated) == (2, 2)
        expected = base.cut(moved.tool).add(implant.tool, 1000.0)
        assert result.evm == expected.evm and np.array_equal(result.table(0), expected.table(0))
