"""The non-destructive tool stack: same result as applying entries one by one, cached tail."""

import numpy as np
import pytest

from volumeevm_addon import EVM, EditStack, ToolOperation, VolumeEVM


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
    operations = [ToolOperation(box, "keep"), ToolOperation(drill, "cut"), ToolOperation(implant, "add", density=3000)]
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
    operations = [ToolOperation(box, "keep"), ToolOperation(implant, "add"), ToolOperation(drill, "cut")]
    stack.evaluate(operations)
    moved = ToolOperation(drill.translate(np.array([5, 0, 0])), "cut")
    result = stack.evaluate(operations[:2] + [moved])
    assert stack.last_recomputed == 1
    mask = head >= 300
    assert result.evm == ((EVM.from_mask(mask) & box) | implant) - moved.tool


def test_largest_part_entry(head, tools):
    drill, box, _ = tools
    base = VolumeEVM.from_array(head, 300)
    result = EditStack(base).evaluate([ToolOperation(drill, "cut"), ToolOperation(operation="largest")])
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
