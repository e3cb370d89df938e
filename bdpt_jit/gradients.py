"""Differentiable rendering: the derivative of a bdpt image with respect to scene parameters
(BSDF and emitter parameters, shape vertex positions), in forward and reverse mode, pass by pass.

Detached sampling in path space. Every random decision (directions, emitter and lens samples,
lobes, roulette) is made without derivatives, and every density and MIS weight is detached.
The vertices are material points of the surfaces (Mitsuba's ``RayFlags.FollowShape``): when a
shape moves, a vertex found on it moves with it, at fixed barycentric coordinates. A path's
contribution in the area measure, Le G f G f ... We, is then a differentiable function of the
parameters at fixed random numbers, and its density in the area measure does not depend on
them (for BSDF and emitter parameters, and for rigid motions of shapes, whose area elements
do not change). So each edge multiplies the throughput by a ratio that is 1 in value and
carries the derivative of that edge's factor: for the edge from x_i to x_{i+1},

    [f_i(x_{i-1} -> x_i -> x_{i+1}) |cos(n_{i+1}, w)| / |x_{i+1} - x_i|^2]_ad / detach(same)

(``edge_ratio``); emission, emitter sampling and escaping rays have ratios of their own. Any
fixed weights that sum to one over the strategies leave every strategy's estimator unbiased,
so the sum of the weighted derivative estimators is an unbiased estimator of the derivative
of the image, as long as the parameter moves no visibility boundary: silhouettes of occluders,
of emitters and of the image's own content are not handled (their boundary terms are missing:
a parameter that moves an edge seen against something else gets a biased derivative there).

Delta vertices (mirrors, smooth glass) with geometry: a delta vertex's outgoing direction is
fixed by its incoming one, so the vertex after it cannot be a material point (moving the vertex
before it would break the law of reflection). In a differentiable pass with geometry, the vertex
after a delta vertex is the intersection of the delta direction computed with derivatives
(``slide``: it slides over its surface as the direction turns), and a ray that leaves the scene
there looks up the environment in that direction (``env_direction_ratio``). That is Veach's
path integral with each specular chain integrated out from its camera-side end, so it is
unbiased for every strategy that traces the chain from the camera: technique ``pt`` (hits and
emitter sampling). The light subpaths of bdpt trace chains from the other end (there the
vertex after the chain, towards the camera, is the ray intersection, and the one before it a
material point): the same path is parametrised in two ways, the derivatives of the two
integrands differ by a divergence term, and MIS weights that mix them leave a bias. So in such
a pass bdpt leaves the strategies that cross a specular chain from the light side out of the
partition of unity (as light tracing's splats are for geometry): ``mis.MIS.camera_chains``, a
camera subpath's d_vc set to 0 at a delta vertex and light subpaths ended at their first delta
vertex.

Not handled, and refused (``check_parameters``, ``check_technique``): sensor parameters, point
and spot light positions, the index of refraction of a smooth dielectric (it turns a delta
lobe), shape parameters with a directionalarea emitter, and shape parameters in scenes with
delta BSDFs with techniques other than ``pt`` and ``bdpt``.

The primal image is never changed: ``dr.replace_grad`` keeps every primal value and only
exchanges gradients.
"""

import drjit as dr
import mitsuba as mi

from . import connect
from .jitmath import safe_div, sel
from .rays import spawn
from .sampling import Sampling

# parameter keys whose derivative bdpt does not compute (see the module docstring)
_REFUSED_LEAVES = ('position', 'direction', 'x_fov', 'focus_distance', 'aperture_radius', 'center', 'radius')
_GEOMETRY_LEAVES = ('vertex_positions', 'vertex_normals', 'to_world')
# BSDFs whose index of refraction turns a delta lobe's direction
_DELTA_IOR = ('SmoothDielectric', 'ThinDielectric')


def _grad_enabled_keys(params):
    out = []
    for key in params.keys():
        try:
            value = params[key]
        except Exception:
            continue
        if dr.grad_enabled(value):
            out.append(key)
    return out


def check_parameters(params, scene=None):
    """Refuse gradient-enabled parameters whose derivative bdpt does not compute."""
    if params is None:
        return
    media = _media(scene)
    for key in _grad_enabled_keys(params):
        if media:
            raise NotImplementedError(
                f"bdpt: gradients with respect to '{key}' are not supported in a scene with participating "
                f"media (the medium {media}): bdpt renders media without derivatives; differentiate this "
                "scene with Mitsuba's prbvolpath")
        leaf = key.split('.')[-1]
        node = params.properties[key][2] if hasattr(params, 'properties') else None
        cls = str(node.class_name()) if node is not None else ''
        why = None
        if leaf in _REFUSED_LEAVES or isinstance(node, mi.Sensor) or (leaf == 'to_world' and isinstance(node, mi.Emitter)):
            why = 'sensor parameters and the placement of point, spot and analytic shapes'
        elif leaf in ('eta', 'int_ior', 'ext_ior') and cls in _DELTA_IOR:
            why = "the index of refraction of a smooth dielectric (it turns a delta lobe's direction)"
        elif (leaf in _GEOMETRY_LEAVES or key.endswith('to_world')) and _delta_emitters(scene):
            why = ('shape geometry in a scene with a directionalarea emitter (its delta direction '
                   'constrains the vertex after it, which the light subpath places)')
        if why is not None:
            raise NotImplementedError(
                f"bdpt: gradients with respect to '{key}' are not supported: {why}. bdpt differentiates "
                "BSDF and emitter values (reflectance, roughness, specular reflectance/transmittance, "
                "radiance, intensity, irradiance, environment texels) and shape vertex positions "
                "(interior derivatives: silhouettes are not handled; in scenes with delta BSDFs with "
                "technique 'pt' only)")


def slides_after_delta(c):
    """A differentiable pass with respect to geometry in a scene with delta BSDFs: the vertex
    after a delta vertex is a ray intersection, not a material point (``edge_ratio``)."""
    return c.ad and c.has_delta and bool(c.ad_geometry)


def check_technique(c):
    """Geometry in a scene with delta BSDFs is differentiated with techniques 'pt' and 'bdpt'
    (the latter without the strategies whose light subpath crosses a delta vertex:
    mis.MIS.camera_chains): refuse the others (called when a pass starts tracing)."""
    if not slides_after_delta(c) or c.strategies.technique in ('pt', 'bdpt'):
        return
    key = c.ad_geometry[0]
    raise NotImplementedError(
        f"bdpt: gradients with respect to '{key}' are not supported with technique "
        f"'{c.strategies.technique}' in a scene with delta (specular) BSDFs: a specular chain pins the "
        "vertex after it to the one before it, and the camera and the light subpaths pin it from opposite "
        "ends (each side's vertex after the chain is a ray intersection, the other side's a material "
        "point). The strategies that cross a chain from the light side and those that cross it from the "
        "camera side parametrise the same paths differently, and MIS weights that mix the two give a "
        "biased derivative. Use technique 'pt' or 'bdpt' (every chain crossed from the camera: unbiased interior "
        "derivative), or differentiate BSDF and emitter values")


def geometry_keys(params):
    """The gradient-enabled shape parameters."""
    if params is None:
        return []
    return [k for k in _grad_enabled_keys(params)
            if k.split('.')[-1] in _GEOMETRY_LEAVES or k.endswith('to_world')]


def _media(scene):
    """The first medium of the scene, named (scene_check.describe_medium), or ''."""
    if scene is None:
        return ''
    from .scene_check import describe_medium, scene_media
    found = scene_media(scene)
    return describe_medium(found[0]) if found else ''


def _delta_emitters(scene):
    """A surface emitter with a delta direction (directionalarea) in the scene."""
    if scene is None:
        return False
    f = mi.EmitterFlags
    return any(mi.has_flag(e.flags(), f.Surface) and mi.has_flag(e.flags(), f.DeltaDirection)
               for e in scene.emitters())


def ratio(x):
    """1 in value, with the derivative of x / detach(x): the factor x of a throughput whose
    value is already in it, differentiated (0 derivative where x is 0)."""
    d = dr.detach(x)
    ok = (d != 0) & dr.isfinite(d)            # an overflowed factor (vertices ~1e-19 apart): no derivative
    q = dr.select(ok, x / dr.select(ok, d, 1.0), 0.0)
    return type(x)(dr.replace_grad(dr.ones(type(x), dr.width(x)), q))   # (keeps mi.Spectrum's type)


_SLIDING = ('p', 'n', 'uv', 't', 'dp_du', 'dp_dv', 'dn_du', 'dn_dv')


def slide(c, si, si_next, wo, active):
    """The vertex after a delta vertex ``si`` (``wo``: its outgoing direction, with derivatives)
    as the intersection of that ray: where a neighbour of the delta vertex moves, the delta
    direction turns and the next vertex slides over its surface (a material point would break
    the law of reflection or refraction). Changes ``si_next`` in place, derivatives only: its
    values stay those of the traced hit (where the re-traced ray finds another primitive, as it
    may at an edge, the hit keeps its material-point derivative)."""
    ray = spawn(si.p, si.n, c.offsets.error(si.p, si.shape), wo, si.time, si.wavelengths)   # rays.py
    hit = c.offsets.intersect(c.scene, ray, active, mi.RayFlags.All)
    same = active & hit.is_valid() & (hit.prim_index == si_next.prim_index) & (hit.shape == si_next.shape)
    for name in _SLIDING:
        old = getattr(si_next, name)
        setattr(si_next, name, dr.select(same, dr.replace_grad(old, getattr(hit, name)), old))
    f_old, f_new = si_next.sh_frame, hit.sh_frame
    si_next.sh_frame = mi.Frame3f(*(dr.select(same, dr.replace_grad(getattr(f_old, a), getattr(f_new, a)),
                                              getattr(f_old, a)) for a in ('s', 't', 'n')))


def env_direction_ratio(c, si, wo, active):
    """A ray that leaves the scene after a delta vertex: the environment's value in the delta
    direction (which turns when a neighbour moves) over its value in the traced direction: 1 in
    value, with the derivative of the direction only (the texels' own derivative cancels: the
    image's environment term carries it)."""
    env = c.scene.environment()
    if env is None:
        return 1.0
    def value(d):
        si_env = dr.zeros(mi.SurfaceInteraction3f)
        si_env.wi, si_env.time, si_env.wavelengths = -d, si.time, si.wavelengths
        return env.eval(si_env, active)
    e_att, e_det = value(wo), value(dr.detach(wo))
    ok = active & (dr.detach(e_det) > 0) & dr.isfinite(dr.detach(e_att))
    q = dr.select(ok, e_att / dr.select(ok, e_det, 1.0), 1.0)
    return type(q)(dr.replace_grad(dr.ones(type(q), dr.width(q)), q))


def emission_ratio(c, e, si1, u_dir, time, active):
    """The light subpath's first edge y0 -> y1: [Le(y0 -> y1) |cos_y0| |cos_y1| / d^2]_ad /
    detach for area emitters, [I(w) |cos_y1| / d^2] for points and spots, [Le(w) |cos_y1|]
    for environments and directional lights (y0 a direction: no distance)."""
    k, emitter = e.kinds, e.emitter
    to = si1.p - e.y0_p
    dist2 = dr.squared_norm(to)
    w = to * dr.rsqrt(dr.select(dist2 > 0, dist2, 1.0))
    w = sel(k.infinite, e.d, w)
    cos1 = dr.abs(dr.dot(si1.n, w))
    value = mi.Spectrum(0.0)
    if k.area is not False:
        si_e = mi.SurfaceInteraction3f(e.si_e)
        si_e.p, si_e.n = e.y0_p, e.y0_n
        sh_n = e.y0_n
        if c.emitters.smooth is not None:       # (smooth-shaded emitter meshes: the side by their shading normal)
            sh_n = dr.select(c.emitters.smooth.rank(emitter, active)[1], e.si_e.sh_frame.n, sh_n)
        si_e.sh_frame = mi.Frame3f(sh_n)
        si_e.wi = si_e.to_local(w)
        le = emitter.eval(si_e, active & k.area)
        value = sel(k.area, le * dr.abs(dr.dot(e.y0_n, w)) * cos1 * safe_div(1.0, dist2), value)
    if getattr(k, 'dir_area', False) is not False:
        # a surface emitting along its normal only (directionalarea): a delta direction, so only
        # the emitted value is differentiated (geometry is refused for it: check_parameters)
        _, le_n = emitter.sample_wavelengths(e.si_e, mi.Float(0.5), active & k.dir_area)   # as endpoints
        value = sel(k.dir_area, le_n * dr.abs(dr.dot(si1.n, e.d)), value)
    if k.delta_pos is not False:
        it = dr.zeros(mi.Interaction3f)
        it.p, it.time, it.wavelengths = si1.p, time, si1.wavelengths
        _, w_pt = emitter.sample_direction(it, u_dir, active & k.delta_pos)    # I(w) / d^2
        value = sel(k.delta_pos, w_pt * cos1, value)
    if k.infinite is not False:
        if k.delta_dir is not False:
            it = dr.zeros(mi.Interaction3f)
            it.p, it.time, it.wavelengths = si1.p, time, si1.wavelengths
            _, w_dir = emitter.sample_direction(it, u_dir, active & k.delta_dir)
            value = sel(k.delta_dir, w_dir * cos1, value)
        if k.env is not False:
            # (eval, not eval_direction: Mitsuba's envmap reads the direction from ds.p - it.p there)
            si_env = dr.zeros(mi.SurfaceInteraction3f)
            si_env.wi, si_env.time = e.d, time                # e.d leaves the environment
            si_env.wavelengths = si1.wavelengths
            value = sel(k.env, emitter.eval(si_env, active & k.env) * cos1, value)
    return mi.Spectrum(dr.select(active, ratio(value), 1.0))


class ADSampling(Sampling):
    """Sampling in a differentiable pass (module docstring): every decision detached, every
    vertex a material point of its surface, each edge's derivative attached to the throughput."""

    def intersect(self, ray, active, primary=False):
        """The hit as a material point of its shape (RayFlags.FollowShape): it moves with the
        shape's parameters. A camera ray's first hit (``primary``) slides along its ray instead:
        a pixel sees through a fixed footprint of directions, so its first vertex is
        parametrised by the direction (solid angle)."""
        c = self.ctx
        if primary:
            check_technique(c)
            return super().intersect(ray, active)
        si = c.offsets.intersect(c.scene, ray, active, mi.RayFlags.All | mi.RayFlags.FollowShape)
        return c.offsets.project_to_triangle(si, active)      # rays.py: the mesh error bound assumes it

    def sample_bsdf(self, bsdf, mode, si, u1, u2, active):
        """Without derivatives: the edge's derivative comes with ``edge_ratio`` once the next
        vertex is known."""
        with dr.suspend_grad():
            return super().sample_bsdf(bsdf, mode, si, u1, u2, active)

    def sample_direct(self, si, u, active):
        """The emitter point is a material point (Mitsuba's sampling with derivatives), the
        density detached, and the weight Le / pdf_w = Le |cos_y| / (d^2 pdf_a) takes the
        derivative of Le |cos_y| / d^2 (area emitters; ``eval_direction`` of a point or spot
        light is already I / d^2, and a directional light's or an environment's value has no
        distance)."""
        c = self.ctx
        ds, w = c.emitters.sample_direct(si, u, active)
        le = ds.emitter.eval_direction(si, ds, active & (ds.pdf > 0))
        k = c.emitters.kinds(ds.emitter)
        geo = sel(k.area, dr.abs(dr.dot(ds.n, ds.d)) * safe_div(1.0, dr.square(ds.dist)), mi.Float(1.0))
        ds.pdf = dr.detach(ds.pdf)
        value = dr.detach(w) * ratio(le * geo)
        if c.emitters.smooth is not None:
            # smooth-shaded emitter meshes (smooth_emitters.py): eval_direction would read the
            # side from ds.n, the triangle's normal; w already holds Le by the shading normal with
            # its derivative, and their points are not differentiated (not sampled by bdpt if so)
            value = dr.select(c.emitters.smooth.rank(ds.emitter, active)[1], w, value)
        return ds, value

    def sample_emission(self, u_sel, u_pos, u_dir, active, wavelengths=None):
        """Everything sampled without derivatives except the emitter point of area emitters,
        a material point of its shape; the emitted value's derivative comes with
        ``first_hit`` (emission_ratio)."""
        c = self.ctx
        check_technique(c)
        with dr.suspend_grad():
            e = super().sample_emission(u_sel, u_pos, u_dir, active, wavelengths)
        if e.kinds.area is not False:
            ps, _, _ = c.emitters.sample_position(e.emitter, c.time, u_pos, e.active & e.kinds.area)
            e.y0_p = sel(e.kinds.area, ps.p, e.origin)
            e.y0_n = sel(e.kinds.area, ps.n, e.n_e)
        else:
            e.y0_p, e.y0_n = e.origin, e.n_e
        return e

    def first_hit(self, e, si, u_dir, active):
        c = self.ctx
        beta = e.beta * emission_ratio(c, e, si, u_dir, c.time, active & si.is_valid())
        # wi from the emitter point (a material point); an infinite emitter's y0 is a direction
        si.wi = sel(e.kinds.infinite, si.wi, si.to_local(dr.normalize(e.y0_p - si.p)))
        return beta, si

    def next_vertex(self, camera_side, v, ray, u, is_delta, beta, active):
        """The next vertex a material point, the edge's derivative factor (``edge_ratio``) in
        the throughput, and its incident direction from ``v``'s position, both with derivatives
        (si.wi from the traced ray has none)."""
        si_next = self.intersect(ray, active)
        beta = beta * self.edge_ratio(camera_side, v, si_next, ray.d, u, is_delta, active)
        si_next.wi = si_next.to_local(dr.normalize(v.si.p - si_next.p))
        return si_next, beta, dr.squared_norm(si_next.p - v.si.p)

    def edge_ratio(self, camera_side, v, si_next, d_escape, u, is_delta, active):
        """The edge from the vertex ``v`` (its wi attached) to the next vertex ``si_next``
        (``d_escape``: the sampled direction, for lanes that left the scene): [f G]_ad / detach.
        Delta lobes: the gradient of the sampled weight (``u``: the lobe and direction samples)."""
        c, si, bsdf = self.ctx, v.si, v.bsdf
        hit = active & si_next.is_valid()
        to_next = si_next.p - si.p
        dist2 = dr.squared_norm(to_next)
        w = dr.select(hit, to_next * dr.rsqrt(dr.select(dist2 > 0, dist2, 1.0)), d_escape)
        if camera_side:
            f, _, _ = connect.eval_camera_vertex(si, bsdf, w, active, None)
        else:
            f, _, _, _ = connect.eval_light_vertex(si, bsdf, w, active, c.exact_adjoint, None)
        g = dr.select(hit, dr.abs(dr.dot(si_next.n, w)) * safe_div(1.0, dist2), 1.0)
        out = ratio(f * g)
        if is_delta is not None:
            mode = connect.CTX_RADIANCE if camera_side else connect.CTX_IMPORTANCE
            bs, w_delta = bsdf.sample(mode, si, u[0], u[1], active & is_delta)
            out = dr.select(is_delta, ratio(w_delta), out)
            if slides_after_delta(c):
                wo = si.to_world(bs.wo)                   # with derivatives: si's position, frame and wi
                slide(c, si, si_next, wo, active & is_delta & hit)
                out = out * env_direction_ratio(c, si, wo, active & is_delta & ~hit)
        return mi.Spectrum(dr.select(active, out, 1.0))
