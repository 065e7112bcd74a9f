"""The one exception type for input the core cannot use.

Readers, builders and file loaders raise :class:`VolumeEVMError` with a message that names the
file (or parameter) and the problem, so that a Blender operator can report it as it is and a
script gets an exception that says what to fix.
"""


class VolumeEVMError(ValueError):
    """Bad input: a corrupt or foreign file, wrong dimensions, NaN densities, an empty region.

    Subclasses ``ValueError`` so that code catching ``ValueError`` for bad arguments also
    catches it.
    """
