"""The light-vertex store: the vertices y_1, y_2, ... of a pass's light subpaths that camera
subpaths connect to (s>=2, t>=2), as packed records in one array. The store owns its layout:
``slot(level, idx)`` is the only place that knows it is level-major (index = level * N + path),
so the same code runs with symbolic loops (one kernel) and with evaluated loops (as Dr.Jit's
AD needs). When ``max_depth`` bounds the subpath the storage is sized exactly; without a bound
the light loop pauses the lanes whose storage is full, the storage grows, and the loop resumes:
no vertex is ever dropped, so every strategy the MIS weights count is really available."""

import drjit as dr
import mitsuba as mi

from .moments import SPLIT_WIDTH
from .vertex import Vertex


# Every field a light vertex can need, in storage order. A scene stores only those its BSDFs
# and shapes read (record_type): scatter and gather cost per word on the CPU (measured: storing
# 35-word records took ~140 ms of a 720 ms render; 25 words +20% samples/s; at most 33 now).
FIELDS = {
    'p': mi.Point3f,          # position
    'err': mi.Float,          # bound on the position's floating-point error (rays.RayOffsets)
    'n': mi.Normal3f,         # geometric normal         (absent: the shading normal, see below)
    'n_s': mi.Normal3f,       # shading normal
    's': mi.Vector3f,         # shading tangent          (absent: any tangent, isotropic BSDFs)
    'uv': mi.Point2f,         # surface parametrisation  (textures)
    'wi': mi.Vector3f,        # direction towards y_{j-1}: local (with s), else world
    'shape': mi.ShapePtr,     # its shape                (mesh attributes)
    'bsdf': mi.BSDFPtr,       # its BSDF
    'prim_index': mi.UInt32,  # triangle                 (mesh attributes)
    'dp_du': mi.Vector3f,     # surface tangents         (normal and bump maps)
    'dp_dv': mi.Vector3f,
    'beta': mi.Spectrum,      # Le / p up to y_j, importance transport (3, 1 or 4 words)
    'd_vcm': mi.Float,        # MIS quantities (mis.py)
    'd_vc': mi.Float,
    'd_vm': mi.Float,         # merging MIS quantity     (technique vcm only)
    'depth': mi.UInt32,       # j: edges from y0         (absent: level + 1, every vertex stored)
    'medium': mi.MediumPtr,   # the medium the subpath reached it in   (scenes with media only)
    'in_medium': mi.UInt32,   # 1: a medium vertex (p, wi and medium; its coefficients evaluated again)
}


_COMPONENTS = {mi.Point3f: 3, mi.Normal3f: 3, mi.Vector3f: 3, mi.Vector4f: 4, mi.Point2f: 2,
               mi.Float: 1, mi.UInt32: 1, mi.ShapePtr: 1, mi.BSDFPtr: 1, mi.MediumPtr: 1,
               mi.Spectrum: dr.size_v(mi.Spectrum),    # RGB 3, monochrome 1, spectral 4
               mi.ArrayXf: SPLIT_WIDTH}                # technique auto's pilot's family vectors (moments.py)


class VertexRecord:
    """One light vertex y_j as connections need it: the fields of its SurfaceInteraction3f that
    BSDFs read, its throughput and its MIS quantities. Subclasses name their fields in
    DRJIT_STRUCT (a subset of FIELDS, chosen by record_type)."""
    DRJIT_STRUCT = {}

    @classmethod
    def make(cls, v, sub):
        """The record of vertex ``v`` (vertex.Vertex) of the light subpath ``sub``
        (transport.Subpath: its throughput, MIS quantities and depth there)."""
        r = cls()
        si, m = v.si, sub.mis
        d_vm = 0.0 * m.d_vc if m.d_vm is None else m.d_vm
        src = {'p': si.p, 'err': v.err, 'n': si.n, 'n_s': si.sh_frame.n, 's': si.sh_frame.s, 'uv': si.uv,
               'wi': si.wi if 's' in cls.DRJIT_STRUCT else si.to_world(si.wi),
               'shape': si.shape, 'bsdf': v.bsdf, 'prim_index': si.prim_index, 'dp_du': si.dp_du,
               'dp_dv': si.dp_dv, 'beta': sub.beta, 'd_vcm': m.d_vcm, 'd_vc': m.d_vc, 'd_vm': d_vm,
               'depth': sub.depth}
        if 'in_medium' in cls.DRJIT_STRUCT:      # (media_path.PathVertex)
            src['medium'], src['in_medium'] = v.medium, dr.select(v.in_medium, mi.UInt32(1), mi.UInt32(0))
        for k in cls.DRJIT_STRUCT:           # unused fields are never evaluated (lazy JIT)
            setattr(r, k, src[k])
        return r

    def vertex(self, time, wavelengths=None):
        """The stored vertex as a vertex.Vertex (``interaction``'s arguments), or a
        media_path.PathVertex in a scene with media."""
        v = Vertex(self.interaction(time, wavelengths), self.bsdf, self.err)
        if 'in_medium' not in self.DRJIT_STRUCT:
            return v
        from .media_path import stored_vertex
        return stored_vertex(v, self.medium, self.in_medium)

    # ---------------------------------------------------------------- packed storage
    # A record is stored as consecutive float words, padded to whole packets of 4: one vertex
    # is written and read with a few 4-wide packet scatters/gathers (Dr.Jit's PacketOps)
    # instead of one scalar scatter/gather per word into separate arrays. Measured on the
    # SmallVCM box: storing light vertices took 256 of 1090 ms per render as separate
    # arrays; packets are ~4x faster to write and to read back.
    @classmethod
    def words(cls):
        return sum(_COMPONENTS[t] for t in cls.DRJIT_STRUCT.values())

    @classmethod
    def packets(cls):
        return (cls.words() + 3) // 4

    @classmethod
    def word_of(cls, name):
        """The position of field ``name``'s first word in a packed record."""
        i = 0
        for k, t in cls.DRJIT_STRUCT.items():
            if k == name:
                return i
            i += _COMPONENTS[t]
        raise KeyError(name)

    def pack(self):
        out = []
        for k, t in self.DRJIT_STRUCT.items():
            x = getattr(self, k)
            if t in (mi.ShapePtr, mi.BSDFPtr, mi.MediumPtr):
                out.append(dr.reinterpret_array(mi.Float, dr.reinterpret_array(mi.UInt32, x)))
            elif t is mi.UInt32:
                out.append(dr.reinterpret_array(mi.Float, x))
            elif t is mi.Float:
                out.append(x)
            else:
                out += [x[i] for i in range(_COMPONENTS[t])]
        return out

    @classmethod
    def unpack(cls, words):
        v = cls()
        i = 0
        for k, t in cls.DRJIT_STRUCT.items():
            m = _COMPONENTS[t]
            if t in (mi.ShapePtr, mi.BSDFPtr, mi.MediumPtr):
                x = dr.reinterpret_array(t, dr.reinterpret_array(mi.UInt32, words[i]))
            elif t is mi.UInt32:
                x = dr.reinterpret_array(mi.UInt32, words[i])
            elif t is mi.Float:
                x = words[i]
            else:
                x = t(*words[i:i + m])
            setattr(v, k, x)
            i += m
        return v

    @classmethod
    def allocate(cls, count):
        """Uninitialised storage for ``count`` records (every read is masked by the stored
        count; zeroing cost ~3% a pass)."""
        return dr.empty(mi.Float, max(count, 1) * cls.packets() * 4)

    @classmethod
    def store(cls, storage, record, slot, active):
        w = record.pack()
        w += [mi.Float(0.0)] * (cls.packets() * 4 - len(w))
        for q in range(cls.packets()):
            dr.scatter(storage, mi.Vector4f(*w[4 * q:4 * q + 4]), slot * cls.packets() + q, active)

    @classmethod
    def load(cls, storage, slot, active):
        w = []
        for q in range(cls.packets()):
            x = dr.gather(mi.Vector4f, storage, slot * cls.packets() + q, active)
            w += [x.x, x.y, x.z, x.w]
        return cls.unpack(w)

    def depth_at(self, level):
        """Edges from y0 to this vertex, stored at ``level`` (0-based)."""
        return self.depth if 'depth' in self.DRJIT_STRUCT else level + 1

    def interaction(self, time, wavelengths=None):
        """The SurfaceInteraction3f that the vertex's BSDF is evaluated at (``wavelengths``: the
        sample's, in spectral variants: those of the camera vertex it is connected to)."""
        f = self.DRJIT_STRUCT
        si = dr.zeros(mi.SurfaceInteraction3f, dr.width(self.p))
        si.t = mi.Float(1.0)
        si.time = time
        if wavelengths is not None:
            si.wavelengths = wavelengths
        si.p = self.p
        si.n = self.n if 'n' in f else self.n_s
        if 's' in f:
            si.sh_frame = mi.Frame3f(self.s, dr.cross(self.n_s, self.s), self.n_s)
            si.wi = self.wi
        else:
            # isotropic BSDFs: any tangent, with wi stored in world space and made local to it
            si.sh_frame = mi.Frame3f(self.n_s)
            si.wi = si.sh_frame.to_local(self.wi)
        if 'uv' in f:
            si.uv = self.uv
        if 'shape' in f:
            si.shape, si.prim_index = self.shape, self.prim_index
        if 'dp_du' in f:
            si.dp_du, si.dp_dv = self.dp_du, self.dp_dv
        return si


def make_record_type(fields):
    name = 'VertexRecord_' + '_'.join(fields)
    return type(name, (VertexRecord,), {'DRJIT_STRUCT': {k: FIELDS[k] for k in FIELDS if k in fields}})


MEDIA_FIELDS = ('medium', 'in_medium')

# every surface field: what a scene the analysis knows nothing about gets (the media fields
# only where the scene has a medium: record_type)
StoredVertex = make_record_type([k for k in FIELDS if k not in MEDIA_FIELDS])


def record_type(needs, merging=False, media=False):
    """The record for a scene: ``needs`` (scene_check.VertexNeeds) says which optional fields
    its BSDFs and shapes read; ``merging``: vertex merging with MIS (technique vcm) reads d_vm;
    ``media``: the scene has participating media (medium vertices, each vertex's medium)."""
    fields = ['p', 'err', 'n_s', 'wi', 'bsdf', 'beta', 'd_vcm', 'd_vc']
    if merging:
        fields.append('d_vm')
    if needs.geometric_normal:
        fields.append('n')
    if needs.tangent:
        fields.append('s')
    if needs.uv:
        fields += ['uv', 'shape', 'prim_index']
    if needs.surface_tangents:
        fields += ['dp_du', 'dp_dv']
    if needs.depth:
        fields.append('depth')
    if media:
        fields += list(MEDIA_FIELDS)
    return make_record_type(fields)


class LightStore:
    """Vertices y_1, y_2, ... of N light subpaths at non-delta surfaces.

    n         light subpaths (one per camera sample of the pass)
    capacity  levels allocated
    record    a VertexRecord type (record_type)
    v         packed records (VertexRecord.allocate) for n * capacity slots
    count     mi.UInt32 per path: vertices stored
    (A plain class, not a dataclass: Dr.Jit would traverse a dataclass referenced in a loop.)"""

    def __init__(self, n, capacity, record=None):
        self.n = n
        self.n_opaque = dr.opaque(mi.UInt32, n)     # a literal would recompile per pass size
        self.capacity = capacity
        self.record = record if record is not None else StoredVertex
        self.v = None
        self.count = None
        self.allocate()

    def allocate(self):
        self.v = self.record.allocate(self.n * self.capacity)
        self.count = dr.zeros(mi.UInt32, self.n)

    def slot(self, level, idx):
        """Where vertex ``level`` (0-based) of light subpath ``idx`` is stored."""
        return level * self.n_opaque + idx

    def stored_slots(self, in_medium=None, lanes=None):
        """The slots that hold a vertex, in increasing order (level-major: by level, then
        light subpath): Dr.Jit's compress of the valid slots. A light subpath fills a few of
        its levels (on the caustic at 256 x 256, max_depth 8, 1.1 vertices in 7), so what is
        built over the stored vertices is built over these (merge.PhotonGrid: the grid over
        every slot took 12% of vcm's kernel time there, 97 ms of 832; light_cache.LightCache).
        ``in_medium`` True or False: those of the vertices inside media or on surfaces only
        (their in_medium word read: the stores of scenes with media). ``lanes``: those of the
        light subpaths of index below it only (merge.MergeSchedule.beam_lanes), None: of all."""
        n_slots = self.n * self.capacity
        if n_slots == 0:
            return dr.zeros(mi.UInt32, 0)
        slot = dr.arange(mi.UInt32, n_slots)
        level = slot // self.n_opaque
        path = slot - level * self.n_opaque
        valid = level < dr.gather(mi.UInt32, self.count, path)
        if lanes is not None:
            valid &= path < lanes
        if in_medium is not None:
            word = slot * (self.record.packets() * 4) + self.record.word_of('in_medium')
            medium = dr.reinterpret_array(mi.UInt32, dr.gather(mi.Float, self.v, word, valid)) != 0
            valid &= medium if in_medium else ~medium
        return dr.compress(valid)

    def grow(self):
        """Double the levels, keeping what is stored (level-major: a plain prefix copy)."""
        old, count = self.v, self.count
        self.capacity *= 2
        self.allocate()
        self.count = count
        dr.scatter(self.v, old, dr.arange(mi.UInt32, dr.width(old)))
        dr.eval(self.v)
