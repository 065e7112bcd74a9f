"""User interface: property groups (``props``) and the sidebar panels (``panels``).

``CLASSES`` lists the classes to register: property groups, UI lists, panels.
"""

from . import panels, props

CLASSES = [*props.CLASSES, *panels.LISTS, *panels.CLASSES]
