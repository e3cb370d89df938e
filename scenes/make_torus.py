"""Writes scenes/torus.ply, the diffuse torus of scenes/torus-in-glass.xml: a triangle mesh of a torus
around the y axis, centred at the origin (major radius 1, minor radius MINOR; the scene scales, tilts
and places it), as binary little-endian PLY with positions and faces only (Mitsuba computes smooth
vertex normals). NU x NV quads, two triangles each: 3072 triangles, about 55 KB.

    python scenes/make_torus.py            # rewrites scenes/torus.ply (deterministic: same bytes each time)
"""

import sys
from pathlib import Path

import numpy as np

NU, NV = 64, 24         # segments around the ring (major) and around the tube (minor)
MINOR = 0.33            # tube radius over ring radius


def torus(nu=NU, nv=NV, minor=MINOR):
    """(vertices (nu*nv, 3) float32, faces (2*nu*nv, 3) int32), faces wound so that their normals point
    out of the tube."""
    u = 2 * np.pi * np.arange(nu) / nu
    v = 2 * np.pi * np.arange(nv) / nv
    uu, vv = np.meshgrid(u, v, indexing='ij')
    ring = 1.0 + minor * np.cos(vv)
    verts = np.stack([ring * np.cos(uu), minor * np.sin(vv), ring * np.sin(uu)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing='ij')
    a = i * nv + j
    b = ((i + 1) % nu) * nv + j
    c = ((i + 1) % nu) * nv + (j + 1) % nv
    d = i * nv + (j + 1) % nv
    faces = np.concatenate([np.stack([a, d, c], -1).reshape(-1, 3), np.stack([a, c, b], -1).reshape(-1, 3)])
    return verts.astype(np.float32), faces.astype(np.int32)


def write_ply(path, verts, faces):
    header = ('ply\nformat binary_little_endian 1.0\ncomment torus for torus-in-glass.xml, written by '
              f'scenes/make_torus.py\nelement vertex {len(verts)}\nproperty float x\nproperty float y\n'
              f'property float z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n')
    face_rec = np.zeros(len(faces), dtype=[('n', 'u1'), ('idx', '<i4', (3,))])
    face_rec['n'] = 3
    face_rec['idx'] = faces
    with open(path, 'wb') as f:
        f.write(header.encode('ascii'))
        f.write(verts.astype('<f4').tobytes())
        f.write(face_rec.tobytes())


def main(argv=None):
    out = Path(__file__).resolve().parent / 'torus.ply'
    verts, faces = torus()
    # outward winding: the first face's normal points away from the tube's centre line
    p = verts[faces[0]]
    n = np.cross(p[1] - p[0], p[2] - p[0])
    centre = p.mean(0)
    ring = centre * np.array([1, 0, 1]) / np.linalg.norm(centre * np.array([1, 0, 1]))
    assert np.dot(n, centre - ring) > 0, 'faces wound inwards'
    write_ply(out, verts, faces)
    print(f'{out}: {len(verts)} vertices, {len(faces)} triangles, {out.stat().st_size} bytes')
    return 0


if __name__ == '__main__':
    sys.exit(main())
