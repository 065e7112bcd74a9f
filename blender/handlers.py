"""The add-on's Blender app handlers, installed and removed in one place.

Each module lists its handlers as ``HANDLERS = (("save_pre", function), ...)``; ``install`` adds
them to ``bpy.app.handlers`` once, ``uninstall`` removes them (the extension's ``unregister``,
also at interpreter exit).
"""

import bpy

_installed = []


def install(handlers):
    """Add ``(event name, function)`` pairs to ``bpy.app.handlers`` (each once)."""
    for event, function in handlers:
        functions = getattr(bpy.app.handlers, event)
        if function not in functions:
            functions.append(function)
            _installed.append((event, function))


def uninstall():
    """Remove every handler ``install`` added."""
    while _installed:
        event, function = _installed.pop()
        functions = getattr(bpy.app.handlers, event)
        while function in functions:
            functions.remove(function)
