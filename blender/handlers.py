"""The add-on's Blender handlers, added and removed in one place: app handlers and the 3D
viewport's draw handlers.

Each module lists its app handlers as ``HANDLERS = (("save_pre", function), ...)``; ``install``
adds them to ``bpy.app.handlers`` once, ``uninstall`` removes them (the extension's
``unregister``, also at interpreter exit). A module that draws over the 3D viewports keeps a
:class:`ViewportDraw` and adds and removes it on register and unregister.
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


class ViewportDraw:
    """A function drawn over every 3D viewport after the scene (``POST_VIEW``) while added: the
    Viewport DVR's and the build preview's draw handlers.

    Attributes
    ----------
    function : callable
        Called with no arguments at each draw of a 3D viewport's region.
    handle : object or None
        Blender's handle of the added draw handler, None while it is not added.
    """

    def __init__(self, function):
        self.function = function
        self.handle = None

    def add(self):
        """Add the draw handler to every 3D viewport (once)."""
        if self.handle is None:
            self.handle = bpy.types.SpaceView3D.draw_handler_add(self.function, (), "WINDOW",
                                                                 "POST_VIEW")

    def remove(self):
        """Remove the draw handler, if it was added."""
        if self.handle is not None:
            bpy.types.SpaceView3D.draw_handler_remove(self.handle, "WINDOW")
            self.handle = None
