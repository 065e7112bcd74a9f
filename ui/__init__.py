"""User interface: the property groups (``props``), the sidebar panels (``panels``, with the one
histogram drawer) and the Render section (``render_panel``).

``CLASSES`` lists the classes to register, in order: property groups, UI lists, panels.
"""

from . import panels, props, render_panel

CLASSES = [*props.CLASSES, *panels.LISTS, *panels.CLASSES, *render_panel.CLASSES]
