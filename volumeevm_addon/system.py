"""What the core needs from the machine: safe file writes, the memory budget, the kernel cache.

A public module for the Blender side and for scripts that manage these themselves (a job
runner, a benchmark); a user who only reads, builds and renders never needs it.

- :func:`write_atomically` / :func:`atomic_target`: every file of ours is written to a
  temporary name and published whole, never replacing a file unasked.
- :func:`available_memory` / :func:`check_memory`: the budget every large allocation is
  checked against first (capped by the environment variable :data:`LIMIT_VARIABLE`).
- :func:`set_kernel_cache_dir` / :func:`set_kernel_compile_hook`: where the compiled kernels
  are cached, and a callback when one compiles (Blender shows it in the status bar).
"""

from ._files import atomic_target, write_atomically
from ._jit import set_kernel_cache_dir, set_kernel_compile_hook
from ._memory import LIMIT_VARIABLE, available_memory, check_memory

__all__ = ["LIMIT_VARIABLE", "atomic_target", "available_memory", "check_memory",
           "set_kernel_cache_dir", "set_kernel_compile_hook", "write_atomically"]
