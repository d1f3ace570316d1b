"""Table entries: a geomjax function under its reference signature, and the public function.

A :class:`BridgedOp` takes the signature of a geomjax function (names, order, ``*`` marker and
defaults from ``inspect.signature``; annotations read in the reference's vocabulary, with the
overrides of its ``_ops.py`` entry) and builds from it the tensor slots and static options of its
:class:`~torch_bridge._lift.LiftedFunction`, the custom op ``geomjax::<name>``: its schema holds the
tensor arguments (``Tensor`` / ``Tensor?``) and the static options (``float``, ``bool``, ``str``,
lists, ...). Python argument forms a schema cannot hold (``radius: float | Tensor``,
``origin: Tensor | Sequence[float]``) are split into a ``Tensor?`` slot and a static slot.
:func:`make_public_function` gives the user-facing function the reference's name, parameters,
defaults and keyword-only marker.
"""

from __future__ import annotations

import ast
import inspect
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import FunctionType, MappingProxyType
from typing import Any, Protocol, cast

import jax
import numpy as np
import torch

from ._dlpack import numpy_dtype, x64_for
from ._lift import NAMESPACE, OPTIONAL_TENSOR, TENSOR, LiftedFunction, prepared

_REQUIRED = object()
_BAD = object()


def _static_normalizer(schema_type: str) -> Callable:
    """Map a Python option to the value a schema slot holds, or ``_BAD`` if it cannot hold it."""
    optional = schema_type.endswith("?")
    base = schema_type.rstrip("?")

    def real(v):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (numbers.Real, torch.SymFloat, torch.SymInt)):
            return _BAD
        if not isinstance(v, numbers.Real):
            return v
        try:
            return float(v)
        except OverflowError:  # a Python int beyond every float: geomjax raises "must be finite"
            return math.inf if v > 0 else -math.inf

    def integer(v):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (numbers.Integral, torch.SymInt)):
            return _BAD
        if not isinstance(v, numbers.Integral):
            return v
        # An int64 slot cannot hold more: geomjax's check then raises its ValueError.
        return int(v) if -(2**63) <= v < 2**63 else _BAD

    def boolean(v):
        return bool(v) if isinstance(v, (bool, np.bool_)) else _BAD

    def string(v):
        return v if isinstance(v, str) else _BAD

    def sequence_of(element):
        def normalize(v):
            if isinstance(v, torch.Tensor) and element is integer and v.ndim == 1 and not v.is_floating_point():
                # e.g. grid_dims given as a tensor: its values are shapes, read on the host.
                v = v.tolist()
            if isinstance(v, (str, bytes)) or not isinstance(v, Sequence):
                return _BAD
            out = tuple(element(x) for x in v)
            return _BAD if any(x is _BAD for x in out) else out

        return normalize

    normalizers = {"float": real, "int": integer, "bool": boolean, "str": string}
    if base.endswith("[]"):
        inner = sequence_of(normalizers[base[:-2]])
    else:
        inner = normalizers[base]
    if optional:
        return lambda v: None if v is None else inner(v)
    return inner


_OPTION_WORDS = {
    "float": "a real number",
    "int": "an integer",
    "bool": "a bool",
    "str": "a string",
    "float[]": "a sequence of real numbers",
    "int[]": "a sequence of integers",
}

_ANNOTATION_TYPES = {"float": "float", "int": "int", "bool": "bool", "str": "str", "Sequence[float]": "float[]", "Sequence[int]": "int[]"}


@dataclass(frozen=True)
class Parameter:
    """One parameter of a public function and where its value goes (tensor slot, static slots)."""

    name: str
    keyword_only: bool
    default: object
    tensor_slot: int | None  # index of its Tensor/Tensor? slot
    static_slot: int | None  # index of its static slot
    static_type: str | None
    optional: bool
    sequence_slot: int | None = None  # index of its sequence static slot (``int | Sequence[int]``)


def _parse_annotation(name: str, annotation: str) -> tuple[bool, str | None, bool, str | None]:
    """``(has_tensor, static_schema_type, optional, sequence_schema_type)`` from an annotation like
    ``float | Tensor``; ``int | Sequence[int]`` gives ``("int", "int[]")`` as the two static forms."""
    has_tensor, optional, statics = False, False, []
    for member in (m.strip() for m in annotation.split("|")):
        if member == "Tensor":
            has_tensor = True
        elif member == "None":
            optional = True
        elif member.startswith("Literal["):
            statics.append("str")
        elif member in _ANNOTATION_TYPES:
            statics.append(_ANNOTATION_TYPES[member])
        else:
            raise ValueError(f"parameter {name}: unsupported annotation member {member!r}")
    forms = sorted(set(statics), key=len)
    if len(forms) == 2 and forms[1] == forms[0] + "[]":
        return has_tensor, forms[0], optional, forms[1]
    if len(forms) > 1:
        raise ValueError(f"parameter {name}: more than one static form in {annotation!r}")
    return has_tensor, (forms[0] if forms else None), optional, None


@dataclass(frozen=True)
class _Declared:
    """A signature as declared: ``(name, annotation, keyword_only, default)`` per parameter."""

    name: str
    parameters: tuple[tuple[str, str, bool, object], ...]
    returns: str


def _parse_signature(signature: str) -> _Declared:
    """Read a signature written out, e.g. ``"f(points: Tensor, *, scale: float = 2.0) -> Tensor"``."""
    tree = ast.parse(f"def {signature}: pass").body[0]
    assert isinstance(tree, ast.FunctionDef)  # the source starts with "def"
    positional, keyword_only = tree.args.args, tree.args.kwonlyargs
    defaults = [None] * (len(positional) - len(tree.args.defaults)) + list(tree.args.defaults)
    defaults += list(tree.args.kw_defaults)
    parameters = tuple(
        (arg.arg, _annotation_source(tree.name, f"parameter {arg.arg}", arg.annotation), i >= len(positional), _REQUIRED if d is None else ast.literal_eval(d))
        for i, (arg, d) in enumerate(zip([*positional, *keyword_only], defaults))
    )
    return _Declared(tree.name, parameters, _annotation_source(tree.name, "the return", tree.returns))


def _annotation_source(function_name: str, what: str, node: ast.expr | None) -> str:
    # Every annotation is needed: it decides the schema type of the slot.
    if node is None:
        raise ValueError(f"{function_name}: {what} has no annotation")
    return ast.unparse(node)


def _tuple_length(node: ast.expr) -> int:
    """The number of elements of a ``tuple[...]`` annotation (``tuple[X]`` has one)."""
    if not isinstance(node, ast.Subscript):
        raise ValueError(f"not a tuple annotation: {ast.unparse(node)!r}")
    return len(node.slice.elts) if isinstance(node.slice, ast.Tuple) else 1


def _is_array_annotation(node: ast.expr, namespace: dict) -> bool:
    """``Float[Array, "..."]`` (any jaxtyping dtype) or a name bound to such a type (``Points``)."""
    if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Tuple) and node.slice.elts:
        first = node.slice.elts[0]
        return isinstance(first, ast.Name) and first.id == "Array"
    if isinstance(node, ast.Name) and node.id in namespace:
        return "jaxtyping" in type(namespace[node.id]).__module__
    return False


def _torch_annotation(annotation: str, namespace: dict) -> str:
    """A geomjax annotation in the reference's vocabulary: every JAX array form becomes ``Tensor``
    and a fixed-length ``tuple[int, ...]`` becomes ``Sequence[int]``."""

    def members(node):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.BitOr):
            return [*members(node.left), *members(node.right)]
        return [node]

    forms = []
    for node in members(ast.parse(annotation, mode="eval").body):
        if _is_array_annotation(node, namespace):
            form = "Tensor"
        elif isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id == "tuple":
            element = node.slice.elts[0] if isinstance(node.slice, ast.Tuple) else node.slice
            form = f"Sequence[{ast.unparse(element)}]"
        else:
            form = ast.unparse(node)
        if form not in forms:
            forms.append(form)
    return " | ".join(forms)


def _derive_signature(function, *, rename, annotations, exclude, returns) -> _Declared:
    """The signature of a geomjax function: names, order, keyword-only marker and defaults as
    geomjax declares them, annotations in the reference's vocabulary (``annotations`` overrides)."""
    namespace = inspect.unwrap(function).__globals__
    parameters = []
    for parameter in inspect.signature(function).parameters.values():
        if parameter.name in exclude:
            continue
        if parameter.kind not in (parameter.POSITIONAL_OR_KEYWORD, parameter.KEYWORD_ONLY):
            raise ValueError(f"{function.__name__}: unsupported parameter kind of {parameter.name}")
        name = rename.get(parameter.name, parameter.name)
        annotation = annotations.get(name) or _torch_annotation(str(parameter.annotation), namespace)
        default = _REQUIRED if parameter.default is parameter.empty else parameter.default
        parameters.append((name, annotation, parameter.kind == parameter.KEYWORD_ONLY, default))
    if returns is None:
        annotation = inspect.signature(function).return_annotation
        tree = ast.parse(str(annotation), mode="eval").body
        if isinstance(tree, ast.Subscript) and isinstance(tree.value, ast.Name) and tree.value.id == "tuple":
            returns = f"tuple[{', '.join(['Tensor'] * _tuple_length(tree))}]"
        else:
            returns = "Tensor" if _is_array_annotation(tree, namespace) else str(annotation)
    return _Declared(function.__name__, tuple(parameters), returns)


class BridgedOp:
    """One table entry: a geomjax function exposed to PyTorch under its reference signature.

    Args:
        signature: the geomjax function whose signature (names, order, ``*`` marker, defaults) the
            op takes, or the signature written out, e.g. ``"displace_points(points: Tensor,
            displacement: Tensor, *, point_weights: Tensor | None = None, implementation: str |
            None = None) -> Tensor"``. Annotations use ``Tensor``, ``None``, ``float``, ``int``,
            ``bool``, ``str``, ``Literal[...]`` and ``Sequence[float | int]``, joined with ``|``;
            the return is ``Tensor`` or ``tuple[Tensor, ...]``. geomjax's annotations are read in
            that vocabulary (every JAX array form is ``Tensor``).
        function: the function to call with the parameters by name (default: ``signature``;
            required when ``signature`` is written out).
        annotations: reference annotations where geomjax's own would give another schema (e.g.
            ``grid_dims: Sequence[int]``, whose integer-tensor form is read on the host).
        rename: parameter names that differ from geomjax's (``{"geomjax_name": "name"}``).
        exclude: geomjax parameters that the reference does not have.
        returns: the return annotation, where geomjax's cannot be read as one.
        nondifferentiable: tensor parameters that must not require grad (``ValueError``).
        dynamic_outputs: for a non-differentiable op with data-dependent output sizes,
            ``f(arguments) -> [(trailing_shape, torch_dtype), ...]`` given the bound arguments by
            name (tensors may be fake); see :class:`LiftedFunction`.
        index_outputs: positions of the integer outputs that the reference returns as int64
            whatever the index dtype of the inputs (face ids, triangles, sample indices); geomjax
            returns int32 unless JAX runs in 64-bit mode.
        prepared: keyword arguments of ``function`` that are built on the host from the call's
            concrete tensors, ``{keyword: build(arguments by name) -> JAX arrays or None}``
            (a mesh's topology, which geomjax builds itself only from concrete arrays, while the
            bridge's programs take every tensor traced); see :func:`torch_bridge._lift.prepared`.
    """

    def __init__(
        self,
        signature: str | Callable,
        function: Callable | None = None,
        *,
        annotations: Mapping[str, str] = MappingProxyType({}),
        rename: Mapping[str, str] = MappingProxyType({}),
        exclude: Sequence[str] = (),
        returns: str | None = None,
        nondifferentiable: Sequence[str] = (),
        dynamic_outputs: Callable[[dict], list] | None = None,
        index_outputs: Sequence[int] = (),
        prepared: Mapping[str, Callable[[dict], Any]] = MappingProxyType({}),
    ):
        self.function: Callable
        self.index_outputs = frozenset(index_outputs)
        self.prepared = dict(prepared)
        if isinstance(signature, str):
            declared = _parse_signature(signature)
            if function is None:
                raise TypeError(f"{declared.name}: a signature written out needs the function to call")
            self.function = function
        else:
            declared = _derive_signature(signature, rename=rename, annotations=annotations, exclude=exclude, returns=returns)
            self.function = signature if function is None else function
        self.name = declared.name
        if declared.returns == "Tensor":
            self.num_outputs, self.single_output = 1, True
        elif declared.returns.startswith("tuple["):
            self.num_outputs = _tuple_length(ast.parse(declared.returns, mode="eval").body)
            self.single_output = False
        else:
            raise ValueError(f"{self.name}: unsupported return annotation {declared.returns!r}")

        # (name, schema type) of each tensor slot and each static slot.
        slots: list[tuple[str, str]] = []
        statics: list[tuple[str, str]] = []
        params: list[Parameter] = []
        for name, annotation, keyword_only, default in declared.parameters:
            has_tensor, static_type, optional, sequence_type = _parse_annotation(name, annotation)
            tensor_slot: int | None = None
            static_slot: int | None = None
            sequence_slot: int | None = None
            schema_type: str | None = None
            if has_tensor:
                tensor_slot = len(slots)
                slots.append((name, OPTIONAL_TENSOR if (optional or static_type) else TENSOR))
            if static_type:
                static_slot = len(statics)
                schema_type = static_type + ("?" if (optional or has_tensor or sequence_type) else "")
                statics.append((f"{name}_value" if has_tensor else name, schema_type))
            if sequence_type:
                sequence_slot = len(statics)
                statics.append((f"{name}_sequence", sequence_type + "?"))
            params.append(
                Parameter(
                    name=name,
                    keyword_only=keyword_only,
                    default=default,
                    tensor_slot=tensor_slot,
                    static_slot=static_slot,
                    static_type=schema_type,
                    optional=optional,
                    sequence_slot=sequence_slot,
                )
            )
        self.parameters = tuple(params)
        unknown = set(nondifferentiable) - {p.name for p in params if p.tensor_slot is not None}
        if unknown:
            raise ValueError(f"{self.name}: nondifferentiable names unknown tensor parameters {sorted(unknown)}")
        self._num_slots, self._num_statics = len(slots), len(statics)
        self._normalizers = tuple(_static_normalizer(p.static_type) if p.static_type is not None else None for p in params)
        self._sequence_normalizers = tuple(_static_normalizer(statics[p.sequence_slot][1]) if p.sequence_slot is not None else None for p in params)
        # The fake kernel's stand-in for a real option it cannot read: the default, else 1.0
        # (for each entry of a sequence).
        real_placeholders: list[float | None] = [None] * len(statics)
        for p in params:
            if p.static_slot is not None:
                default = p.default
                real_placeholders[p.static_slot] = float(default) if isinstance(default, (int, float)) and not isinstance(default, bool) else 1.0
        self.lifted = LiftedFunction(
            self.name,
            self._call_geomjax,
            slots,
            statics,
            self.num_outputs,
            nondifferentiable=[p.tensor_slot for p in params if p.name in nondifferentiable],
            # first and second derivatives, under torch.compile too
            eager_vjp_levels=0 if dynamic_outputs is not None else 2,
            dynamic_outputs=None if dynamic_outputs is None else lambda slots, statics: dynamic_outputs(self._geomjax_kwargs(slots, statics)),
            prepare=self._prepare if self.prepared else None,
            real_placeholders=real_placeholders,
        )

    def _prepare(self, slots, statics) -> dict:
        arguments = self._geomjax_kwargs(slots, statics)
        return {keyword: build(arguments) for keyword, build in self.prepared.items()}

    def _geomjax_kwargs(self, slots, statics) -> dict:
        kwargs = {}
        for p in self.parameters:
            value = None
            if p.tensor_slot is not None:
                value = slots[p.tensor_slot]
            if value is None and p.static_slot is not None:
                value = statics[p.static_slot]
            if value is None and p.sequence_slot is not None:
                value = statics[p.sequence_slot]
            kwargs[p.name] = value
        return kwargs

    def _call_geomjax(self, slots, statics):
        kwargs = self._geomjax_kwargs(slots, statics)
        if self.prepared:
            built = prepared() or {}  # nothing when traced for output shapes only
            kwargs.update({keyword: built.get(keyword) for keyword in self.prepared})
        result = self.function(**kwargs)
        return (result,) if self.single_output else tuple(result)

    def bind(self, values):
        """Split Python arguments (in signature order) into tensor slots and static options."""
        slots = [None] * self._num_slots
        statics = [None] * self._num_statics
        for p, normalize, normalize_sequence, value in zip(self.parameters, self._normalizers, self._sequence_normalizers, values):
            if p.tensor_slot is not None and isinstance(value, torch.Tensor):
                slots[p.tensor_slot] = value
            elif normalize is not None:
                normalized, slot = normalize(value), p.static_slot
                if normalized is _BAD and normalize_sequence is not None:
                    normalized, slot = normalize_sequence(value), p.sequence_slot
                if normalized is _BAD:
                    self._raise_for_option(p, values)
                statics[slot] = normalized
            elif value is not None or not p.optional:
                raise TypeError(f"{self.name}: {p.name} must be a torch.Tensor{' or None' if p.optional else ''}, got {type(value).__name__}")
        return tuple(slots), tuple(statics)

    def _raise_for_option(self, parameter: Parameter, values):
        """An option the schema cannot hold: raise geomjax's own error for it, if it has one.

        Under ``torch.compile`` geomjax cannot run at trace time; the bridge's ``TypeError`` is
        raised instead (with ``fullgraph=True`` Dynamo reports it as an ``Unsupported`` error that
        quotes this message).
        """
        value = values[self.parameters.index(parameter)]
        assert parameter.static_type is not None  # bind() calls this for parameters with a static slot only
        base = parameter.static_type.rstrip("?")
        expected = _OPTION_WORDS.get(base, base)
        if parameter.sequence_slot is not None:
            expected += " or " + _OPTION_WORDS[base + "[]"]
        if parameter.tensor_slot is not None:
            expected += " or a torch.Tensor"
        elif parameter.optional:
            expected += " or None"
        error = TypeError(f"{self.name}: {parameter.name} must be {expected}, got {type(value).__name__}")
        if torch.compiler.is_compiling() or self.lifted.dynamic_outputs is not None:
            raise error  # geomjax cannot be traced here (under compile, or an eager-only op)
        tensors = {p.name: v for p, v in zip(self.parameters, values) if p.tensor_slot is not None and isinstance(v, torch.Tensor)}
        others = {p.name: v for p, v in zip(self.parameters, values) if p.name not in tensors}
        structs = {n: jax.ShapeDtypeStruct(tuple(t.shape), numpy_dtype(t.dtype)) for n, t in tensors.items()}
        with x64_for(tensors.values()):
            jax.eval_shape(lambda arrays: self.function(**arrays, **others), structs)
        raise error

    def __call__(self, *values):
        slots, statics = self.bind(values)
        outputs = self.lifted.apply(slots, statics)
        if self.index_outputs:
            # Outside the custom op (whose outputs keep geomjax's dtypes): eager calls and compiled
            # graphs alike return int64, and fake tensors report it.
            outputs = [o.to(torch.int64) if i in self.index_outputs else o for i, o in enumerate(outputs)]
        return outputs[0] if self.single_output else tuple(outputs)


class PublicFunction(Protocol):
    """A user-facing function, with the table entry it fronts as ``bridged_op``."""

    bridged_op: BridgedOp

    def __call__(self, *args: Any, **kwargs: Any) -> Any: ...


def with_bridged_op(function: Callable[..., Any], op: BridgedOp) -> PublicFunction:
    """``function`` with ``function.bridged_op = op``."""
    # Function objects take new attributes at run time, which their static type does not list;
    # the Protocol declares the one added here.
    public = cast(PublicFunction, function)
    public.bridged_op = op
    return public


def publish_wrapper(function: Callable[..., Any], op: BridgedOp, op_differs: str) -> PublicFunction:
    """``function``, a hand-written public front of ``op`` (which adds what a custom op cannot
    carry), as a torch_bridge function: its module, ``bridged_op`` and the op's public docstring,
    saying how the custom op's arguments differ (``op_differs``, a parenthesised remark)."""
    function.__module__ = "torch_bridge"
    custom_op = f"custom op ``torch.ops.{NAMESPACE}.{op.name}``"
    function.__doc__ = public_docstring(op).replace(custom_op, f"{custom_op} {op_differs}", 1)
    return with_bridged_op(function, op)


def make_public_function(op: BridgedOp) -> PublicFunction:
    """The user-facing function: the reference's name, parameters, defaults and ``*`` marker."""
    parts: list[str] = []
    names: list[str] = []
    namespace: dict[str, Any] = {"_call": op.__call__}  # the globals of the generated source
    star_written = False
    for p in op.parameters:
        if p.keyword_only and not star_written:
            parts.append("*")
            star_written = True
        if p.default is _REQUIRED:
            parts.append(p.name)
        else:
            namespace[f"_default_{p.name}"] = p.default
            parts.append(f"{p.name}=_default_{p.name}")
        names.append(p.name)
    source = f"def {op.name}({', '.join(parts)}):\n    return _call({', '.join(names)})\n"
    exec(compile(source, f"<torch_bridge.{op.name}>", "exec"), namespace)
    function: FunctionType = namespace[op.name]
    function.__module__ = "torch_bridge"
    function.__qualname__ = op.name
    function.__doc__ = public_docstring(op)
    return with_bridged_op(function, op)


def public_docstring(op: BridgedOp) -> str:
    # geomjax's doc without its JAX example (the torch_bridge package docstring has a torch one).
    geomjax_doc = inspect.cleandoc(op.function.__doc__ or "").split("\nExample")[0].rstrip()
    summary = geomjax_doc.splitlines()[0] if geomjax_doc else op.name
    return (
        f"{summary}\n\n"
        f"PyTorch front of :func:`geomjax.{op.name}`: same parameters, defaults, values, errors and "
        "gradients, with ``torch.Tensor`` inputs and outputs (zero-copy through DLPack). It is the "
        f"custom op ``torch.ops.{NAMESPACE}.{op.name}`` with autograd (any order the JAX path supports), "
        "a fake kernel for ``torch.compile(fullgraph=True)``, and ``torch.library.opcheck`` coverage. "
        '``implementation="torch"`` selects the portable JAX path.'
        + (" Index outputs (face ids, triangles, sample indices) are int64 tensors, as in the reference." if op.index_outputs else "")
        + f"\n\ngeomjax documentation:\n\n{geomjax_doc}"
    )
