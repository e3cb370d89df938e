"""The walks' loops, recorded once.

Dr.Jit records a symbolic loop by running its body in Python. With its flag OptimizeLoops (on
by default) it then looks for state variables that the body left unchanged or set to the same
literal, and records the body a second time without them (drjit-core's jit_var_loop_end:
"re-recording loop ... to eliminate redundant loop state variables"); the kernel is the better
for it, as the literals it then sees fold (without the second recording, OptimizeLoops off, pt's
kernel on scenes/veach-mis.xml ran 4% slower). Every walk has such variables: the time, the
derivatives that ray_intersect leaves at zero, the merging quantities where nothing merges, a
flag that a scene without delta BSDFs never sets. So every render recorded each walk twice (pt's
walk: 3.2 ms of a render's 9.3 ms of Python on veach-mis at 128 x 128; bdpt's walks and
connections 12.8 ms).

``while_once`` records a walk once with the kernel of Dr.Jit's second recording. It records
with OptimizeLoops off for the walk (on for the loops inside its body), applies Dr.Jit's rule
itself after the body (a leaf of the state that comes out as the variable that went in, or as a
literal equal to its value before the loop, is constant) and remembers the constant leaves per
label and signature of the state (the leaves' paths, types and literal-ness). Where it learns
something new it stops the recording (Dr.Jit discards it with its side effects) and records
again; the next render of that signature keeps those leaves out of the loop state from the
start and hands the body their values from before the loop, literals that the kernel folds as
in Dr.Jit's second recording. Each recording checks that the body leaves them unchanged; where
one changes (a scene whose state has the same signature but another body), it is learnt as
variable and the loop recorded again. The first render of a signature records a walk two or
three times (a constant can show only once another is kept out: the ray's time after the
hit's), each later render once; no kernel is compiled for a stopped recording. Objects that
Dr.Jit traverses whole (the sampler) stay loop state: their unchanged words (the independent
sampler's stream constant) are phi nodes that LLVM folds. Only where Dr.Jit records symbolic
loops with its optimisation (its default flags) and the pass has no derivatives (Dr.Jit's AD
records loops its own way); elsewhere it is dr.while_loop.
"""

import copy

import drjit as dr

ONCE = True     # False: each loop as dr.while_loop (for side-by-side measurements)
MAX_ROUNDS = 8  # recordings of a loop to learn its constant leaves, then dr.while_loop
_CONSTANT = {}  # (label, the state's signature) -> paths of the leaves a loop leaves unchanged


class _Relearn(Exception):
    """What was learnt about a loop's leaves was wrong: ``varies`` (paths kept out of the state
    that the body changed) or ``constant`` (paths in the state that it left unchanged)."""

    def __init__(self, varies=frozenset(), constant=frozenset()):
        super().__init__("loop state to learn again")
        self.varies, self.constant = frozenset(varies), frozenset(constant)


def leaves(x, path=(), out=None):
    """[(path, array)] of each one-dimensional Dr.Jit array in ``x`` (tuples, DRJIT_STRUCTs,
    and arrays of arrays such as a Vector3f), depth first; other values are not leaves."""
    out = [] if out is None else out
    kind, arg = _kind(type(x))
    if kind == 'leaf':
        out.append((path, x))
    elif kind == 'tuple':
        for i, y in enumerate(x):
            leaves(y, path + (i,), out)
    elif kind == 'array':
        for i in range(arg):
            leaves(x[i], path + (i,), out)
    elif kind == 'struct':
        for k in arg:
            leaves(getattr(x, k), path + (k,), out)
    return out


def assemble(x, value_at, path=()):
    """A copy of ``x`` (as ``leaves`` walks it) whose leaf at each path p is value_at(p, leaf)."""
    kind, arg = _kind(type(x))
    if kind == 'leaf':
        return value_at(path, x)
    if kind == 'tuple':
        return tuple(assemble(y, value_at, path + (i,)) for i, y in enumerate(x))
    if kind == 'array':
        return type(x)(*(assemble(x[i], value_at, path + (i,)) for i in range(arg)))
    if kind == 'struct':    # Mitsuba's structs copy by their constructor, the project's by copy.copy
        y = type(x)(x) if type(x).__module__.startswith('mitsuba') else copy.copy(x)
        for k in arg:
            setattr(y, k, assemble(getattr(x, k), value_at, path + (k,)))
        return y
    return x


_KINDS = {}


def _kind(t):
    """How ``leaves`` walks a value of type ``t``: ('leaf', None) a one-dimensional Dr.Jit array;
    ('tuple', None); ('array', n) an array of n arrays; ('struct', field names) a DRJIT_STRUCT;
    (None, None) not at all."""
    if t not in _KINDS:
        k = (None, None)
        if t is tuple:          # (not a named tuple: Dr.Jit's loops do not traverse those either)
            k = ('tuple', None)
        elif hasattr(t, 'DRJIT_STRUCT'):
            k = ('struct', tuple(t.DRJIT_STRUCT))
        elif dr.is_jit_v(t) and not dr.is_tensor_v(t):
            n = dr.size_v(t)
            if dr.depth_v(t) == 1:
                k = ('leaf', None)
            elif n > 0:
                k = ('array', n)
        _KINDS[t] = k
    return _KINDS[t]


def same(a, b):
    """Whether the loop body's leaf ``a`` is the value ``b`` it had before the loop: the same
    variable, or both literals of one value (what Dr.Jit would remove from the state)."""
    if a.index == b.index:
        return True
    lit = dr.VarState.Literal
    if a.state != lit or b.state != lit or type(a) is not type(b):
        return False
    x, y = a[0], b[0]
    return x == y or (x != x and y != y)


def signature(label, state):
    """The key of what was learnt about a loop: its label and its state's leaves (paths, types,
    literal or not)."""
    return label, tuple((p, type(a), a.state == dr.VarState.Literal) for p, a in leaves(state))


def while_once(label, objects, state, cond, body, enabled=True):
    """dr.while_loop over ``objects`` (a tuple of objects Dr.Jit traverses whole, such as a
    sampler) and ``state`` (a tuple of arrays and DRJIT_STRUCTs), recorded once (module
    docstring). ``cond(objects, state)`` -> the lanes that go on; ``body(objects, state)`` ->
    (objects, state), the same structure. ``enabled``: False in passes with derivatives.
    Returns (objects, state) after the loop."""
    if not (enabled and ONCE and dr.flag(dr.JitFlag.SymbolicLoops) and dr.flag(dr.JitFlag.OptimizeLoops)):
        return dr.while_loop((objects, state), cond, body, label=label)
    key = signature(label, state)
    if len(key[1]) != len(dr.detail.collect_indices(state)):    # arrays that leaves does not walk
        return dr.while_loop((objects, state), cond, body, label=label)
    for _ in range(MAX_ROUNDS):
        try:
            return _record(key, objects, state, cond, body)
        except RuntimeError as e:
            cause = e
            while cause is not None and not isinstance(cause, _Relearn):
                cause = cause.__cause__
            if cause is None:
                raise
            varies, constant = cause.varies, cause.constant
            # (not kept: the exception's traceback holds the frames of the render that called this
            # loop, its light store and all, in a reference cycle that only Python's garbage
            # collector would free; the next render then allocated fresh memory: docs/light-cache.md,
            # thirty-third session)
            cause = None
            _CONSTANT[key] = (_CONSTANT[key] - varies) | constant
    _CONSTANT.pop(key, None)
    return dr.while_loop((objects, state), cond, body, label=label)


def _record(key, objects, state, cond, body):
    """One recording of while_once's loop, with the leaves learnt constant for ``key`` kept out
    of the loop state (and OptimizeLoops off for this loop, on for the loops in its body).
    Raises _Relearn from the body where what was learnt does not hold."""
    outer = dict(leaves(state))
    const = _CONSTANT.setdefault(key, frozenset())
    var = [p for p in outer if p not in const]

    def unpack(vals):
        got = dict(zip(var, vals))
        return assemble(state, lambda p, x: got.get(p, outer[p]))

    def cond_(objs, *vals):
        return cond(objs, unpack(vals))

    def body_(objs, *vals):
        with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, True):
            objs, out = body(objs, unpack(vals))
        got = dict(leaves(out))
        if got.keys() != outer.keys():
            raise RuntimeError(f"loop '{key[0]}': the body changed the state's structure")
        varies = {p for p in const if not same(got[p], outer[p])}
        constant = {p for p, v in zip(var, vals) if same(got[p], v) or same(got[p], outer[p])}
        if varies or constant:
            raise _Relearn(varies, constant)
        return (objs, *(got[p] for p in var))

    with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False):
        objs, *vals = dr.while_loop((objects, *(outer[p] for p in var)), cond_, body_, label=key[0])
    return objs, unpack(vals)
