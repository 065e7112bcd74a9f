"""The public API documents itself: numpydoc sections that match the code, keyword-only options.

Walks every callable a user reaches without a private name: the names of
``volumeevm_addon.__all__`` and of its public sub-packages' ``__all__`` (``model``,
``rendering``, ``readers``, ``system``, ``phantoms``, ``metrics``), and the public methods and
properties of their classes. Each must have a docstring
whose "Parameters" section names every parameter (a class's constructor parameters in the class
docstring; a record's fields may be its "Attributes"), a "Returns" section when its body
returns a value ("Yields" for a generator) and a "Raises" section naming every exception its
body raises itself. The rules read the code (the signature and the body's
``return``/``yield``/``raise`` statements), so the documentation cannot drift from it.
:func:`~volumeevm_addon.render`'s "Other Parameters" must list exactly the options
:func:`~volumeevm_addon.rendering.render_options` gives for each method, with the same defaults.
"""

import ast
import builtins
import dataclasses
import inspect
import re
import textwrap

import pytest

import volumeevm_addon
from volumeevm_addon import (
    METHODS,
    Camera,
    Shading,
    TransferFunction,
    Volume,
    metrics,
    model,
    phantoms,
    readers,
    render,
    rendering,
    system,
)
from volumeevm_addon.model import ToolOperation
from volumeevm_addon.rendering import render_options

#: The public sub-packages and modules, each with the prefix its names are reached by.
MODULES = ((volumeevm_addon, ""), (model, "model."), (rendering, "rendering."),
           (readers, "readers."), (system, "system."), (phantoms, "phantoms."),
           (metrics, "metrics."))


def _public_callables():
    """``{name: (owner class or None, object)}``; properties are their ``property`` object."""
    found = {}
    for module, prefix in MODULES:
        for name in module.__all__:
            obj = getattr(module, name)
            if not (inspect.isclass(obj) or inspect.isfunction(obj)):
                continue
            found[prefix + name] = (None, obj)
            if not inspect.isclass(obj):
                continue
            for attr, raw in vars(obj).items():
                if attr.startswith("_"):
                    continue
                if isinstance(raw, (classmethod, staticmethod)):
                    raw = raw.__func__
                if isinstance(raw, property) or inspect.isfunction(raw):
                    found[f"{prefix}{name}.{attr}"] = (obj, raw)
    return found


PUBLIC = _public_callables()


def _sections(doc):
    """numpydoc sections of a cleaned docstring: ``{title: [lines]}`` (a title is a line
    followed by a line of dashes as long)."""
    lines = doc.splitlines()
    sections, title = {"": []}, ""
    i = 0
    while i < len(lines):
        if (i + 1 < len(lines) and lines[i].strip() and set(lines[i + 1].strip()) == {"-"}
                and len(lines[i + 1].strip()) == len(lines[i].strip())):
            title = lines[i].strip()
            sections[title] = []
            i += 2
            continue
        sections[title].append(lines[i])
        i += 1
    return sections


def _entries(lines):
    """Names of the entries of a Parameters-like section: unindented ``name : type`` lines
    (``a, b : type`` documents both); the description lines below are indented."""
    names = []
    for line in lines:
        if line.strip() and not line[0].isspace():
            names += [n.strip() for n in line.split(" : ")[0].split(",")]
    return names


def _body_statements(function):
    """The ``return``, ``yield`` and ``raise`` nodes of ``function``'s own body (not those of
    functions or classes defined inside it)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(function)))
    found = []

    def visit(node):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)):
                continue
            if isinstance(child, (ast.Return, ast.Yield, ast.YieldFrom, ast.Raise)):
                found.append(child)
            visit(child)

    visit(tree.body[0])
    return found


def _raised(function):
    """Names of the exception classes ``function``'s body raises itself (``raise E(...)``)."""
    names = set()
    for node in _body_statements(function):
        if isinstance(node, ast.Raise) and node.exc is not None:
            target = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
            if not isinstance(target, ast.Name):
                continue
            value = function.__globals__.get(target.id, getattr(builtins, target.id, None))
            if inspect.isclass(value) and issubclass(value, BaseException):
                names.add(target.id)
    return names


def _returns_value(function):
    """Whether ``function``'s body returns something other than None."""
    return any(isinstance(node, ast.Return) and node.value is not None
               and not (isinstance(node.value, ast.Constant) and node.value.value is None)
               for node in _body_statements(function))


def _yields(function):
    """Whether ``function`` is a generator."""
    return any(isinstance(node, (ast.Yield, ast.YieldFrom)) for node in _body_statements(function))


def _signature_parameters(obj, owner):
    """Parameter names the signature has (less ``self``/``cls``)."""
    names = []
    for p in inspect.signature(obj).parameters.values():
        if owner is not None and p.name in ("self", "cls") and not names:
            continue
        names.append({p.VAR_POSITIONAL: "*", p.VAR_KEYWORD: "**"}.get(p.kind, "") + p.name)
    return names


def _constructors(cls):
    """The class's own ``__init__``/``__post_init__`` (dataclasses make their ``__init__``)."""
    return [f for name, f in vars(cls).items() if name in ("__init__", "__post_init__")
            and inspect.isfunction(f) and f.__code__.co_filename != "<string>"]


@pytest.mark.parametrize("name", sorted(PUBLIC))
def test_numpydoc_sections(name):
    owner, obj = PUBLIC[name]
    doc = inspect.cleandoc((obj.fget if isinstance(obj, property) else obj).__doc__ or "")
    assert doc.strip(), f"{name}: no docstring"
    assert doc.splitlines()[0].strip(), f"{name}: the docstring must start with a summary line"
    if isinstance(obj, property):
        return
    sections = _sections(doc)
    is_exception = inspect.isclass(obj) and issubclass(obj, BaseException)
    if is_exception:
        return
    parameters = _signature_parameters(obj, owner)
    # A record's fields (a dataclass) may be documented as its Attributes instead.
    titles = ("Parameters", "Attributes") if dataclasses.is_dataclass(obj) else ("Parameters",)
    if parameters:
        assert any(t in sections for t in titles), f"{name}: parameters {parameters} but no " \
                                                   f"{' or '.join(titles)} section"
        documented = {n for t in titles for n in _entries(sections.get(t, []))}
        missing = set(parameters) - documented
        assert not missing, f"{name}: {' or '.join(titles)} does not document {sorted(missing)}"
    functions = _constructors(obj) if inspect.isclass(obj) else [obj]
    raised = set().union(*(_raised(f) for f in functions)) if functions else set()
    if raised:
        assert "Raises" in sections, f"{name}: raises {sorted(raised)} but has no Raises section"
        undocumented = raised - set(_entries(sections["Raises"]))
        assert not undocumented, f"{name}: Raises does not name {sorted(undocumented)}"
    if inspect.isclass(obj):
        return
    if _yields(obj):
        assert "Yields" in sections, f"{name}: a generator without a Yields section"
    elif _returns_value(obj):
        assert "Returns" in sections, f"{name}: returns a value but has no Returns section"


# Options are keyword-only: for each callable, the parameters that may be given by position.
POSITIONAL = {
    Camera: ("projection", "matrix_world"),
    Camera.orthographic: ("matrix_world", "ortho_scale"),
    Camera.perspective: ("matrix_world", "lens_mm"),
    Volume: ("array",),
    Shading: (),
    ToolOperation: ("tool", "operation"),
    TransferFunction: ("points",),
    TransferFunction.table: ("self",),
    TransferFunction.straight_table: ("self",),
    TransferFunction.preintegrated_table: ("self",),
    TransferFunction.quantize: ("self", "densities"),
    render: ("vevm", "camera", "tf"),
}


@pytest.mark.parametrize("function", list(POSITIONAL), ids=lambda f: f.__qualname__)
def test_options_are_keyword_only(function):
    parameters = inspect.signature(function).parameters.values()
    positional = tuple(p.name for p in parameters if p.kind == p.POSITIONAL_OR_KEYWORD)
    assert positional == POSITIONAL[function]


def _render_option_docs():
    """``{option: {method: default}}`` from render()'s "Other Parameters", whose entries'
    descriptions start with a sentence such as: Default ``262144`` (raycast), ``8192``
    (reference, splat). Values are Python literals."""
    descriptions, name = {}, None
    for line in _sections(inspect.cleandoc(render.__doc__))["Other Parameters"]:
        if line.strip() and not line[0].isspace():
            name = line.split(" : ")[0].strip()
            descriptions[name] = ""
        elif name is not None:
            descriptions[name] += " " + line.strip()
    options = {}
    for name, text in descriptions.items():
        text = text.strip()
        assert text.startswith("Default "), f"{name}: starts {text[:40]!r}, not 'Default ...'"
        options[name] = {}
        for value, methods in re.findall(r"``([^`]+)`` \(([^)]*)\)", text.split(").")[0] + ")"):
            for method in methods.split(","):
                options[name][method.strip()] = ast.literal_eval(value)
    return options


def test_render_documents_every_methods_options():
    documented = _render_option_docs()
    for method in METHODS:
        have = {name: methods[method] for name, methods in documented.items() if method in methods}
        assert have == render_options(method), method
    assert set().union(*documented.values()) <= set(METHODS)


def test_top_level_is_the_users_and_moved_names_still_work_with_a_warning():
    """About 20 names a user calls at the top; the sub-packages' names do not overlap; a name
    moved to a sub-package still works from the top with a DeprecationWarning naming its new
    place."""
    assert 15 <= len(volumeevm_addon.__all__) <= 25
    places = {}
    for module, prefix in MODULES[1:]:
        for name in module.__all__:
            places.setdefault(name, []).append(prefix)
    assert {name: where for name, where in places.items() if len(where) > 1} == {}
    for name, place in volumeevm_addon._MOVED.items():
        assert name not in volumeevm_addon.__all__
        assert name in getattr(volumeevm_addon, place).__all__
        with pytest.warns(DeprecationWarning, match=f"volumeevm_addon.{place}.{name}"):
            old = getattr(volumeevm_addon, name)
        assert old is getattr(getattr(volumeevm_addon, place), name)
    with pytest.raises(AttributeError, match="no_such_name"):
        getattr(volumeevm_addon, "no_such_name")
