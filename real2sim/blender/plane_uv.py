"""Texture coordinates MuJoCo gives a plane (no bpy here: build_scene.py uses it for the floor's
UVs, and tests/python/test_blender.py checks it against MuJoCo's own render)."""


def plane_st(x, y, size, repeat, uniform):
    """(s, t) of the point (x, y) in a plane's frame. MuJoCo (3.12 and later) gives a finite
    plane of half sizes sx, sy the coordinates s = rx (x / sx + 1) / 2, t = ry (1 - y / sy) / 2,
    with rx, ry its material's texrepeat (a value <= 0 counts as 1), multiplied first by sx, sy
    when texuniform is set: the texture repeats rx times across the plane, or rx / 2 times per
    metre when uniform. An infinite plane (a size of 0) has generated coordinates instead,
    s = rx x / 2 - 1/2 and t = -ry y / 2 - 1/2 (x, y in metres). Works on floats and on numpy
    arrays alike."""
    rx, ry = (float(v) if v > 0 else 1.0 for v in repeat)
    sx, sy = float(size[0]), float(size[1])
    if sx > 0 and sy > 0:
        if uniform:
            rx, ry = rx * sx, ry * sy
        return 0.5 * rx * (x / sx + 1.0), 0.5 * ry * (1.0 - y / sy)
    return 0.5 * rx * x - 0.5, -0.5 * ry * y - 0.5
