//! URDF `<mesh>` files: where a filename points ([`package_search_path`], [`resolve`]; the
//! sim-host's MJCF compiler uses the same two), what a file holds ([`read_mesh`]) and capsules
//! that contain it ([`bounding_capsule`], [`bounding_capsules`]). Files are read when a model is
//! built, never in the tick.
//!
//! Formats: STL (binary or ASCII), OBJ (vertices and face, line and point elements), MuJoCo's
//! binary MSH, and COLLADA (`X.dae`) through the OBJ parts `robots/assets.py` converted it into
//! (`X.dae.parts/parts.txt`, one `FILE R G B A` line per part). A malformed file is an error
//! naming the file and the line (binary formats: the triangle or vertex), never a panic.

use std::path::{Path, PathBuf};

use nalgebra::{Point3, SymmetricEigen, Vector2, Vector3};

/// Extra package roots for `package://` mesh paths, searched before the defaults (`:`-separated).
pub const PACKAGE_PATH_ENV: &str = "R2G_PACKAGE_PATH";

/// Where `package://NAME/…` is looked up, in order: the folders of `$R2G_PACKAGE_PATH`, then the
/// `packages/` folder of the URDF's own folder and of each folder above it (so `robots/packages/`,
/// where `scripts/setup-venv.sh` unpacks the mesh wheels, serves every URDF under `robots/`).
/// A root serves NAME when it holds a folder NAME.
pub fn package_search_path(urdf: &Path) -> Vec<PathBuf> {
    let mut roots: Vec<PathBuf> = std::env::var_os(PACKAGE_PATH_ENV)
        .map(|v| std::env::split_paths(&v).filter(|p| !p.as_os_str().is_empty()).collect())
        .unwrap_or_default();
    let dir = urdf.parent().map(Path::to_path_buf).unwrap_or_default();
    let dir = std::fs::canonicalize(&dir).unwrap_or(dir);
    for a in dir.ancestors() {
        let p = a.join("packages");
        if p.is_dir() && !roots.contains(&p) {
            roots.push(p);
        }
    }
    roots
}

/// The file a URDF mesh filename names (it exists), or why not: `package://NAME/PATH` on
/// `search`, `file://ABSOLUTE`, or a path relative to the folder of `urdf` (the URDF file).
pub fn resolve(filename: &str, urdf: &Path, search: &[PathBuf]) -> Result<PathBuf, String> {
    let path = if let Some(rest) = filename.strip_prefix("package://") {
        let (pkg, rel) =
            rest.split_once('/').ok_or_else(|| "package:// names no file inside the package".to_string())?;
        let Some(root) = search.iter().find(|r| r.join(pkg).is_dir()) else {
            return Err(format!("no package '{pkg}' on the search path (set {PACKAGE_PATH_ENV}, or run scripts/setup-venv.sh for the shipped ones)"));
        };
        root.join(pkg).join(rel)
    } else if let Some(abs) = filename.strip_prefix("file://") {
        PathBuf::from(abs)
    } else {
        urdf.parent().unwrap_or(Path::new(".")).join(filename)
    };
    if path.is_file() {
        Ok(path)
    } else {
        Err(format!("file {} does not exist", path.display()))
    }
}

/// The converted parts of a COLLADA file `X.dae`: each OBJ file in `X.dae.parts/` with its
/// material colour, as `X.dae.parts/parts.txt` lists them.
pub fn converted_parts(dae: &Path) -> Result<Vec<(PathBuf, [f64; 4])>, String> {
    let dir = dae.with_file_name(format!("{}.parts", dae.file_name().and_then(|n| n.to_str()).unwrap_or_default()));
    let list = dir.join("parts.txt");
    let text = std::fs::read_to_string(&list).map_err(|_| {
        format!(
            "{} is COLLADA, which MuJoCo cannot read, and has no converted parts ({} is missing): run `.venv/bin/python robots/assets.py convert {}`",
            dae.display(),
            list.display(),
            dae.parent().unwrap_or(Path::new(".")).display()
        )
    })?;
    let mut parts = Vec::new();
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        let f: Vec<&str> = line.split_whitespace().collect();
        let rgba: Vec<f64> = f.iter().skip(1).filter_map(|v| v.parse().ok()).collect();
        if f.len() != 5 || rgba.len() != 4 || !dir.join(f[0]).is_file() {
            return Err(format!("{}: bad line '{line}' (want FILE R G B A, FILE beside it)", list.display()));
        }
        parts.push((dir.join(f[0]), [rgba[0], rgba[1], rgba[2], rgba[3]]));
    }
    if parts.is_empty() {
        return Err(format!("{} lists no parts", list.display()));
    }
    Ok(parts)
}

/// A mesh file that cannot be read: the file, the line (1-based; for binary STL the triangle,
/// 0-based, is in `detail`) and what is wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{}{}: {detail}", file.display(), line.map(|l| format!(":{l}")).unwrap_or_default())]
pub struct MeshError {
    pub file: PathBuf,
    pub line: Option<usize>,
    pub detail: String,
}

fn fail<T>(file: &Path, line: Option<usize>, detail: impl Into<String>) -> Result<T, MeshError> {
    Err(MeshError { file: file.into(), line, detail: detail.into() })
}

/// A triangle mesh: vertices and triangles (indices into them). Polygons are split into fans;
/// an OBJ line element is a triangle with a repeated corner, a point element one with all three.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub points: Vec<Point3<f64>>,
    pub triangles: Vec<[u32; 3]>,
}

impl Mesh {
    /// Applies `f` to every vertex.
    pub fn map(mut self, f: impl Fn(&Point3<f64>) -> Point3<f64>) -> Self {
        self.points.iter_mut().for_each(|p| *p = f(p));
        self
    }

    fn append(&mut self, other: Mesh) {
        let base = self.points.len() as u32;
        self.points.extend(other.points);
        self.triangles.extend(other.triangles.into_iter().map(|t| t.map(|i| i + base)));
    }
}

/// A mesh file, in the file's own units and frame. By the extension: `.stl`, `.obj`, `.msh`, or
/// `.dae` (all its converted parts together, see [`converted_parts`]). At least one vertex, all
/// finite, every triangle naming existing vertices; otherwise an error naming the file.
pub fn read_mesh(path: &Path) -> Result<Mesh, MeshError> {
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    let mesh = if ext == "dae" {
        let parts = converted_parts(path).map_err(|d| MeshError { file: path.into(), line: None, detail: d })?;
        let mut all = Mesh::default();
        for (part, _) in parts {
            all.append(read_mesh(&part)?);
        }
        all
    } else {
        let bytes = std::fs::read(path).or_else(|e| fail(path, None, format!("cannot read: {e}")))?;
        match ext.as_str() {
            "stl" => parse_stl(path, &bytes)?,
            "obj" => parse_obj(path, &bytes)?,
            "msh" => parse_msh(path, &bytes)?,
            _ => return fail(path, None, format!("unknown mesh format '{ext}' (STL, OBJ, MSH or DAE)")),
        }
    };
    if mesh.points.is_empty() {
        return fail(path, None, "the mesh has no vertices");
    }
    Ok(mesh)
}

fn f32_at(b: &[u8], at: usize) -> f32 {
    f32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

/// STL's triangle soup with equal corners merged (exact comparison).
#[derive(Default)]
struct Soup {
    mesh: Mesh,
    index: std::collections::HashMap<[u64; 3], u32>,
}

impl Soup {
    fn corner(&mut self, v: [f64; 3]) -> u32 {
        let Self { mesh, index } = self;
        *index.entry(v.map(f64::to_bits)).or_insert_with(|| {
            mesh.points.push(Point3::from(v));
            mesh.points.len() as u32 - 1
        })
    }
}

/// Binary STL when the size is exactly 84 + 50 × the triangle count in the header (a binary
/// header may itself start with "solid"), else ASCII STL.
pub fn parse_stl(path: &Path, b: &[u8]) -> Result<Mesh, MeshError> {
    let mut soup = Soup::default();
    if b.len() >= 84 && b.len() as u64 == 84 + 50 * u64::from(u32_at(b, 80)) {
        for (t, tri) in b[84..].chunks_exact(50).enumerate() {
            let mut corners = [0; 3];
            for (k, c) in corners.iter_mut().enumerate() {
                let v = [0, 1, 2].map(|i| f64::from(f32_at(tri, 12 + 12 * k + 4 * i)));
                if !v.iter().all(|x| x.is_finite()) {
                    return fail(path, None, format!("binary STL triangle {t}: vertex {k} is not finite: {v:?}"));
                }
                *c = soup.corner(v);
            }
            soup.mesh.triangles.push(corners);
        }
        return Ok(soup.mesh);
    }
    let Ok(text) = std::str::from_utf8(b) else {
        return fail(
            path,
            None,
            format!(
                "neither binary STL ({} bytes, not 84 + 50 x the triangle count) nor ASCII STL (not text)",
                b.len()
            ),
        );
    };
    let (mut in_loop, mut solid) = (false, false);
    let mut corners: Vec<u32> = Vec::with_capacity(3);
    for (n, line) in text.lines().enumerate() {
        let n = Some(n + 1);
        let t: Vec<&str> = line.split_whitespace().collect();
        let Some(&first) = t.first() else { continue };
        match (first, t.len()) {
            ("solid", _) if !solid => solid = true,
            ("endsolid", _) if solid && !in_loop => solid = false,
            // Normals are not used; degenerate facets may carry NaN ones.
            ("facet", 5)
                if solid && !in_loop && t[1] == "normal" && t[2..].iter().all(|s| s.parse::<f64>().is_ok()) => {}
            ("outer", 2) if solid && !in_loop && t[1] == "loop" => {
                in_loop = true;
                corners.clear();
            }
            ("vertex", 4) if in_loop && corners.len() < 3 => {
                let Some(v) = numbers(&t[1..]) else {
                    return fail(path, n, format!("bad vertex line '{}'", line.trim()));
                };
                corners.push(soup.corner(v));
            }
            ("endloop", 1) if in_loop && corners.len() == 3 => {
                in_loop = false;
                soup.mesh.triangles.push([corners[0], corners[1], corners[2]]);
            }
            ("endfacet", 1) if solid && !in_loop => {}
            _ => return fail(path, n, format!("unexpected ASCII STL line '{}'", line.trim())),
        }
    }
    if solid {
        return fail(path, None, "ASCII STL ends inside a solid (no endsolid)");
    }
    if soup.mesh.triangles.is_empty() && !text.trim_start().starts_with("solid") {
        return fail(path, None, format!("not an STL file ({} bytes, no 'solid' line)", b.len()));
    }
    Ok(soup.mesh)
}

/// Exactly three finite numbers.
fn numbers(t: &[&str]) -> Option<[f64; 3]> {
    let v: Vec<f64> = t.iter().filter_map(|s| s.parse::<f64>().ok()).filter(|x| x.is_finite()).collect();
    (t.len() == 3 && v.len() == 3).then(|| [v[0], v[1], v[2]])
}

/// Wavefront OBJ: `v x y z [w]` or `v x y z r g b`; face (`f`), line (`l`) and point (`p`)
/// elements must name vertices that exist (1-based; negative counts back from the last one
/// read); other statements are the usual attribute and grouping ones, anything else is an error.
pub fn parse_obj(path: &Path, b: &[u8]) -> Result<Mesh, MeshError> {
    let Ok(text) = std::str::from_utf8(b) else { return fail(path, None, "OBJ is not UTF-8 text") };
    let mut mesh = Mesh::default();
    // Elements as (line, vertex indices as written, made absolute), checked once all is read.
    let mut elements: Vec<(usize, Vec<i64>)> = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let t: Vec<&str> = line.split_whitespace().collect();
        let Some(&first) = t.first() else { continue };
        match first {
            "v" => {
                let v: Vec<f64> =
                    t[1..].iter().filter_map(|s| s.parse::<f64>().ok()).filter(|x| x.is_finite()).collect();
                if !matches!(t.len(), 4 | 5 | 7) || v.len() != t.len() - 1 {
                    return fail(path, Some(n + 1), format!("bad vertex line '{}'", line.trim()));
                }
                mesh.points.push(Point3::new(v[0], v[1], v[2]));
            }
            "f" | "l" | "p" => {
                let want = match first {
                    "f" => 3,
                    "l" => 2,
                    _ => 1,
                };
                if t.len() - 1 < want {
                    return fail(path, Some(n + 1), format!("'{first}' needs {want} vertices or more"));
                }
                let mut ids = Vec::with_capacity(t.len() - 1);
                for e in &t[1..] {
                    let Some(i) = e.split('/').next().and_then(|s| s.parse::<i64>().ok()).filter(|&i| i != 0) else {
                        return fail(path, Some(n + 1), format!("bad vertex reference '{e}'"));
                    };
                    ids.push(if i < 0 { mesh.points.len() as i64 + i + 1 } else { i });
                }
                elements.push((n + 1, ids));
            }
            "vn" | "vt" | "vp" | "o" | "g" | "s" | "usemtl" | "mtllib" => {}
            _ if first.starts_with('#') => {}
            _ => return fail(path, Some(n + 1), format!("unknown OBJ statement '{first}'")),
        }
    }
    let count = mesh.points.len() as i64;
    for (line, ids) in elements {
        if let Some(i) = ids.iter().find(|&&i| i < 1 || i > count) {
            return fail(path, Some(line), format!("vertex {i} does not exist ({count} vertices)"));
        }
        let ids: Vec<u32> = ids.iter().map(|&i| (i - 1) as u32).collect();
        let last = ids.len() - 1;
        match ids.len() {
            1 => mesh.triangles.push([ids[0]; 3]),
            2 => mesh.triangles.push([ids[0], ids[1], ids[1]]),
            // Polyline (`l`) segments and polygon fans both stay inside the elements' hulls.
            _ => mesh.triangles.extend((1..last).map(|k| [ids[0], ids[k], ids[k + 1]])),
        }
    }
    Ok(mesh)
}

/// MuJoCo's binary MSH: four int32 counts (vertices, normals, texture coordinates, faces), then
/// the float arrays and the int32 faces; the size must match the counts exactly.
pub fn parse_msh(path: &Path, b: &[u8]) -> Result<Mesh, MeshError> {
    if b.len() < 16 {
        return fail(path, None, format!("MSH shorter than its 16-byte header ({} bytes)", b.len()));
    }
    let c = [0, 4, 8, 12].map(|at| i32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]]));
    let want = c.iter().zip([3, 3, 2, 3]).try_fold(16u64, |s, (&n, k)| u64::try_from(n).ok().map(|n| s + 4 * k * n));
    if want != Some(b.len() as u64) {
        return fail(path, None, format!("MSH counts {c:?} do not match the file size ({} bytes)", b.len()));
    }
    let nv = c[0] as usize;
    let mut mesh = Mesh { points: Vec::with_capacity(nv), triangles: Vec::with_capacity(c[3] as usize) };
    for i in 0..nv {
        let v = [0, 1, 2].map(|k| f64::from(f32_at(b, 16 + 12 * i + 4 * k)));
        if !v.iter().all(|x| x.is_finite()) {
            return fail(path, None, format!("MSH vertex {i} is not finite: {v:?}"));
        }
        mesh.points.push(Point3::from(v));
    }
    let faces = 16 + 4 * (3 * nv + 3 * c[1] as usize + 2 * c[2] as usize);
    for f in 0..c[3] as usize {
        let mut tri = [0u32; 3];
        for (k, corner) in tri.iter_mut().enumerate() {
            let i = i32::from_le_bytes(u32_at(b, faces + 12 * f + 4 * k).to_le_bytes());
            if i < 0 || i as usize >= nv {
                return fail(path, None, format!("MSH face {f} names vertex {i} of {nv}"));
            }
            *corner = i as u32;
        }
        mesh.triangles.push(tri);
    }
    Ok(mesh)
}

/// A capsule: the segment `a`–`b` widened by `radius` (a sphere when `a == b`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Capsule {
    pub a: Point3<f64>,
    pub b: Point3<f64>,
    pub radius: f64,
}

impl Capsule {
    /// Distance from `p` to the capsule's axis segment.
    pub fn axis_distance(&self, p: &Point3<f64>) -> f64 {
        let d = self.b - self.a;
        let len2 = d.norm_squared();
        let s = if len2 > 0.0 { ((p - self.a).dot(&d) / len2).clamp(0.0, 1.0) } else { 0.0 };
        (p - (self.a + d * s)).norm()
    }

    pub fn volume(&self) -> f64 {
        let r = self.radius;
        std::f64::consts::PI * r * r * ((self.b - self.a).norm() + 4.0 / 3.0 * r)
    }
}

/// Added to a bounding capsule's radius so that it still holds every point once the runtime
/// places it in single precision (parry3d works in f32: about 1e-7 m of rounding per metre).
pub const F32_SLACK_M: f64 = 1e-6;

/// A capsule that contains every point (and so, being convex, their convex hull: the whole mesh
/// solid), or `None` for no points or a non-finite one.
///
/// For each candidate axis direction (the three principal axes of the points, and the three
/// frame axes, which meshes are often modelled along), the axis line is placed at the centre of
/// the smallest circle around the points projected across it (Welzl), which gives the radius;
/// the segment is then as short as that radius allows (each point's end cap must reach it). The
/// candidate of least volume wins, and its axis is then tilted in steps (0.1 rad, halved down to
/// 1 mrad) while that lowers the volume. Its radius is finally recomputed as the largest distance
/// of a point from the segment, plus [`F32_SLACK_M`], so containment never rests on rounding.
/// Not the minimal capsule in general (a local search from six starting axes).
pub fn bounding_capsule(points: &[Point3<f64>]) -> Option<Capsule> {
    if points.is_empty() || !points.iter().all(|p| p.coords.iter().all(|v| v.is_finite())) {
        return None;
    }
    let (mut d, mut best) = rough_capsule(points)?;
    // Refine the axis: tilt it while that lowers the volume, halving the tilt when no tilt does.
    let mut step = 0.1;
    while step > 1e-3 {
        let u = d.cross(&if d.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() }).normalize();
        let v = d.cross(&u);
        let tilted = [u, -u, v, -v]
            .into_iter()
            .map(|w| (d + w * step).normalize())
            .map(|e| (e, capsule_along(points, &e)))
            .min_by(|x, y| x.1.volume().total_cmp(&y.1.volume()));
        match tilted {
            Some((e, c)) if c.volume() < best.volume() => (d, best) = (e, c),
            _ => step /= 2.0,
        }
    }
    let radius = points.iter().map(|p| best.axis_distance(p)).fold(0.0, f64::max) + F32_SLACK_M;
    Some(Capsule { radius, ..best })
}

/// A part of a mesh and a capsule around it.
type Piece = (Mesh, Capsule);

/// The least-volume capsule over the candidate axes alone, and its axis.
fn rough_capsule(points: &[Point3<f64>]) -> Option<(Vector3<f64>, Capsule)> {
    if points.is_empty() || !points.iter().all(|p| p.coords.iter().all(|v| v.is_finite())) {
        return None;
    }
    candidate_axes(points)
        .into_iter()
        .map(|d| (d, capsule_along(points, &d)))
        .min_by(|x, y| x.1.volume().total_cmp(&y.1.volume()))
}

/// Most capsules [`bounding_capsules`] puts around one mesh (more would leave pieces bounded by
/// three cut planes, where the argument that the capsules hold the solid no longer holds).
pub const MAX_CAPSULES_PER_MESH: usize = 3;

/// A cut is made only if it shrinks the mesh's total capsule volume by this fraction at least.
pub const MIN_GAIN_PER_CAPSULE: f64 = 0.10;

/// One to `max` capsules whose union contains `mesh`: every vertex and every point of every
/// triangle (and so the solid, for a closed mesh). `None` for a mesh without vertices or with a
/// non-finite one.
///
/// One capsule is [`bounding_capsule`] of all vertices, which also holds their convex hull (the
/// shape MuJoCo collides a mesh geom as). More come from cutting the mesh in two by a plane,
/// again and again (greedy bisection): each round tries, for every piece, planes across each of
/// its candidate axes (those of [`bounding_capsule`], without its refinement) at every 5 % of its
/// length, and makes the cut that shrinks the total capsule volume most, as long as that removes at least
/// [`MIN_GAIN_PER_CAPSULE`] of it. A piece is the part of the mesh on one side of its planes,
/// with triangles clipped at each cut (a clipped triangle is a convex polygon whose corners are
/// the piece's vertices, so a capsule around them holds it): the union of the pieces' capsules
/// holds the mesh's surface, though not necessarily its convex hull. With at most 3 capsules a
/// piece is bounded by at most two cut planes; from any point of a closed mesh's solid inside
/// such a region a ray along the planes (or their common line) leaves the solid through the
/// surface in the region, so the solid's part is in the hull of the surface's part there, and
/// inside the capsule too. A mesh without triangles (bare points) gets one capsule. Finally every
/// vertex is checked against the result, and the nearest capsule grows to hold any that rounding
/// left out.
pub fn bounding_capsules(mesh: &Mesh, max: usize) -> Option<Vec<Capsule>> {
    let max = max.clamp(1, MAX_CAPSULES_PER_MESH);
    // The search compares capsules over the candidate axes only; the pieces' final capsules
    // are then refined.
    let rough = |p: &[Point3<f64>]| rough_capsule(p).map(|(_, c)| c);
    let mut pieces = vec![(mesh.clone(), rough(&mesh.points)?)];
    while pieces.len() < max && !mesh.triangles.is_empty() {
        let total: f64 = pieces.iter().map(|(_, c)| c.volume()).sum();
        // (piece, its halves, volume removed)
        let mut best: Option<(usize, [Piece; 2], f64)> = None;
        for (k, (piece, cap)) in pieces.iter().enumerate() {
            for d in candidate_axes(&piece.points) {
                let t: Vec<f64> = piece.points.iter().map(|p| p.coords.dot(&d)).collect();
                let (t0, t1) = t.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| (a.min(x), b.max(x)));
                for i in 1..20 {
                    let [lo, hi] = split(piece, &t, t0 + (t1 - t0) * f64::from(i) / 20.0);
                    let (Some(a), Some(b)) = (rough(&lo.points), rough(&hi.points)) else {
                        continue;
                    };
                    let gain = cap.volume() - a.volume() - b.volume();
                    if best.as_ref().is_none_or(|x| gain > x.2) {
                        best = Some((k, [(lo, a), (hi, b)], gain));
                    }
                }
            }
        }
        match best {
            Some((k, [lo, hi], gain)) if gain >= MIN_GAIN_PER_CAPSULE * total => {
                pieces[k] = lo;
                pieces.push(hi);
            }
            _ => break,
        }
    }
    let mut caps: Vec<Capsule> = pieces.iter().map(|(p, _)| bounding_capsule(&p.points)).collect::<Option<_>>()?;
    for p in &mesh.points {
        let (k, gap) =
            caps.iter().map(|c| c.axis_distance(p) - c.radius).enumerate().min_by(|a, b| a.1.total_cmp(&b.1))?;
        if gap > 0.0 {
            caps[k].radius = caps[k].axis_distance(p) + F32_SLACK_M;
        }
    }
    Some(caps)
}

/// The parts of `mesh` with `t` (each vertex's position along some axis) at most and at least
/// `c`: vertices on each side (those on the plane in both), and each triangle clipped to each
/// side, the clipped polygon split into a fan with the crossings of its edges as new vertices.
fn split(mesh: &Mesh, t: &[f64], c: f64) -> [Mesh; 2] {
    let mut out = [Mesh::default(), Mesh::default()];
    // Index of each vertex in each part, if it is there.
    let mut at = [vec![u32::MAX; t.len()], vec![u32::MAX; t.len()]];
    for (side, part) in out.iter_mut().enumerate() {
        for (i, p) in mesh.points.iter().enumerate() {
            if (side == 0 && t[i] <= c) || (side == 1 && t[i] >= c) {
                at[side][i] = part.points.len() as u32;
                part.points.push(*p);
            }
        }
    }
    for tri in &mesh.triangles {
        for (side, part) in out.iter_mut().enumerate() {
            let keep = |i: usize| if side == 0 { t[i] <= c } else { t[i] >= c };
            let mut poly: Vec<u32> = Vec::with_capacity(4);
            for e in 0..3 {
                let (a, b) = (tri[e] as usize, tri[(e + 1) % 3] as usize);
                if keep(a) {
                    poly.push(at[side][a]);
                }
                if (t[a] - c) * (t[b] - c) < 0.0 {
                    let x = mesh.points[a] + (mesh.points[b] - mesh.points[a]) * ((c - t[a]) / (t[b] - t[a]));
                    part.points.push(x);
                    poly.push(part.points.len() as u32 - 1);
                }
            }
            for k in 1..poly.len().saturating_sub(1) {
                part.triangles.push([poly[0], poly[k], poly[k + 1]]);
            }
            if poly.len() == 1 || poly.len() == 2 {
                // A corner or an edge touching the plane: keep it as a degenerate triangle.
                part.triangles.push([poly[0], poly[poly.len() - 1], poly[poly.len() - 1]]);
            }
        }
    }
    out
}

/// The principal axes of `points` and the frame axes.
fn candidate_axes(points: &[Point3<f64>]) -> Vec<Vector3<f64>> {
    let n = points.len() as f64;
    let centroid = points.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / n;
    let cov = points.iter().fold(nalgebra::Matrix3::zeros(), |s, p| {
        let d = p.coords - centroid;
        s + d * d.transpose()
    }) / n;
    let eig = SymmetricEigen::new(cov);
    (0..3)
        .map(|i| eig.eigenvectors.column(i).into_owned())
        .chain([Vector3::x(), Vector3::y(), Vector3::z()])
        .filter_map(|d| d.try_normalize(1e-12))
        .collect()
}

/// The bounding capsule with axis direction `d` (unit), as [`bounding_capsule`] describes.
fn capsule_along(points: &[Point3<f64>], d: &Vector3<f64>) -> Capsule {
    let across = if d.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let u = d.cross(&across).normalize();
    let v = d.cross(&u);
    let flat: Vec<Vector2<f64>> = points.iter().map(|p| Vector2::new(p.coords.dot(&u), p.coords.dot(&v))).collect();
    let (centre, _) = enclosing_circle(&flat);
    let r = flat.iter().map(|q| (q - centre).norm()).fold(0.0, f64::max);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (p, q) in points.iter().zip(&flat) {
        let t = p.coords.dot(d);
        let cap = (r * r - (q - centre).norm_squared()).max(0.0).sqrt();
        lo = lo.min(t + cap);
        hi = hi.max(t - cap);
    }
    if lo > hi {
        // Every point is within `r` of one point of the axis: a sphere.
        let mid = (lo + hi) / 2.0;
        (lo, hi) = (mid, mid);
    }
    let at = |t: f64| Point3::from(u * centre.x + v * centre.y + d * t);
    Capsule { a: at(lo), b: at(hi), radius: r }
}

/// The smallest circle around `pts` (Welzl's incremental algorithm over a fixed shuffle, so the
/// result is deterministic): its centre and radius.
fn enclosing_circle(pts: &[Vector2<f64>]) -> (Vector2<f64>, f64) {
    let mut p = pts.to_vec();
    let mut s = 0x9E37_79B9_7F4A_7C15u64;
    for i in (1..p.len()).rev() {
        s = s.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        p.swap(i, (s >> 33) as usize % (i + 1));
    }
    let scale = p.iter().map(|q| q.norm()).fold(1e-9, f64::max);
    let eps = 1e-12 * scale;
    let inside = |c: &(Vector2<f64>, f64), q: &Vector2<f64>| (q - c.0).norm() <= c.1 + eps;
    let two = |a: &Vector2<f64>, b: &Vector2<f64>| ((a + b) / 2.0, (a - b).norm() / 2.0);
    let mut c = (p[0], 0.0);
    for i in 1..p.len() {
        if inside(&c, &p[i]) {
            continue;
        }
        c = (p[i], 0.0);
        for j in 0..i {
            if inside(&c, &p[j]) {
                continue;
            }
            c = two(&p[i], &p[j]);
            for k in 0..j {
                if !inside(&c, &p[k]) {
                    c = three(&p[i], &p[j], &p[k]);
                }
            }
        }
    }
    c
}

/// The circle through three points; for (nearly) collinear ones, the circle on the farthest pair.
fn three(a: &Vector2<f64>, b: &Vector2<f64>, c: &Vector2<f64>) -> (Vector2<f64>, f64) {
    let (ab, ac) = (b - a, c - a);
    let det = 2.0 * (ab.x * ac.y - ab.y * ac.x);
    if det.abs() <= 1e-18 * ab.norm_squared().max(ac.norm_squared()) {
        let pairs = [(a, b), (a, c), (b, c)];
        let (x, y) =
            pairs.into_iter().max_by(|p, q| (p.0 - p.1).norm().total_cmp(&(q.0 - q.1).norm())).unwrap_or((a, b));
        return ((x + y) / 2.0, (x - y).norm() / 2.0);
    }
    let (l1, l2) = (ab.norm_squared(), ac.norm_squared());
    let off = Vector2::new(ac.y * l1 - ab.y * l2, ab.x * l2 - ac.x * l1) / det;
    (a + off, off.norm())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh, empty folder under the system temp folder.
    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("r2g-mesh-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).expect("temp dir");
        d
    }

    fn binary_stl(tris: &[[[f32; 3]; 3]]) -> Vec<u8> {
        let mut b = vec![0u8; 80];
        b.extend((tris.len() as u32).to_le_bytes());
        for t in tris {
            b.extend([0f32; 3].iter().flat_map(|v| v.to_le_bytes()));
            b.extend(t.iter().flatten().flat_map(|v| v.to_le_bytes()));
            b.extend([0u8; 2]);
        }
        b
    }

    const TETRA: [[[f32; 3]; 3]; 4] = [
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]],
        [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]],
    ];

    #[test]
    fn binary_stl_merges_corners() {
        let m = parse_stl(Path::new("t.stl"), &binary_stl(&TETRA)).expect("parse");
        assert_eq!(m.points.len(), 4);
        assert_eq!(m.triangles.len(), 4);
        // A binary header may begin with "solid": the size decides.
        let mut b = binary_stl(&TETRA);
        b[..5].copy_from_slice(b"solid");
        assert_eq!(parse_stl(Path::new("t.stl"), &b).expect("parse").points.len(), 4);
    }

    #[test]
    fn ascii_stl_reads_and_names_the_bad_line() {
        let good = "solid t\n facet normal 0 0 1\n  outer loop\n   vertex 0 0 0\n   vertex 1 0 0\n   vertex 0 1 0\n  endloop\n endfacet\nendsolid t\n";
        let m = parse_stl(Path::new("a.stl"), good.as_bytes()).expect("parse");
        assert_eq!((m.points.len(), m.triangles.len()), (3, 1));
        let bad = good.replace("vertex 1 0 0", "vertex 1 zero 0");
        let e = parse_stl(Path::new("a.stl"), bad.as_bytes()).unwrap_err();
        assert_eq!(e.line, Some(5));
        assert!(e.to_string().starts_with("a.stl:5: bad vertex line 'vertex 1 zero 0'"), "{e}");
        let two = good.replace("   vertex 0 1 0\n", "");
        assert_eq!(parse_stl(Path::new("a.stl"), two.as_bytes()).unwrap_err().line, Some(6), "a loop of 2 corners");
        let open = good.replace("endsolid t\n", "");
        assert!(parse_stl(Path::new("a.stl"), open.as_bytes()).unwrap_err().to_string().contains("no endsolid"));
        let nan = good.replace("vertex 0 0 0", "vertex nan 0 0");
        assert_eq!(parse_stl(Path::new("a.stl"), nan.as_bytes()).unwrap_err().line, Some(4));
    }

    #[test]
    fn broken_binary_stl_is_an_error() {
        let mut b = binary_stl(&TETRA);
        b.truncate(b.len() - 7);
        b[0] = 0xff; // not text either
        let e = parse_stl(Path::new("cut.stl"), &b).unwrap_err();
        assert!(e.to_string().contains("neither binary STL"), "{e}");
        let mut b = binary_stl(&TETRA);
        b[84 + 50 + 12 + 4..84 + 50 + 12 + 8].copy_from_slice(&f32::INFINITY.to_le_bytes());
        let e = parse_stl(Path::new("inf.stl"), &b).unwrap_err();
        assert!(e.to_string().contains("triangle 1: vertex 0 is not finite"), "{e}");
        assert!(parse_stl(Path::new("e.stl"), b"").is_err());
    }

    #[test]
    fn obj_reads_polygons_and_checks_references() {
        let text = "# c\nmtllib x.mtl\no a\nv 0 0 0\nv 1 0 0\nv 1 1 0 1.0\nv 0 1 0 0.5 0.5 0.5\nvn 0 0 1\nvt 0 0\ns off\nusemtl m\nf 1/1/1 2//1 3 4\nf -4 -3 -2\nl 1 3\n";
        let m = parse_obj(Path::new("q.obj"), text.as_bytes()).expect("parse");
        assert_eq!(m.points.len(), 4);
        // The quad as a fan of two, the triangle, the line as a degenerate triangle.
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3], [0, 1, 2], [0, 2, 2]]);
        for (bad, line, what) in [
            ("v 0 0\n", 1, "bad vertex line"),
            ("v 0 0 x\n", 1, "bad vertex line"),
            ("v 0 0 0\nf 1 2 3\n", 2, "vertex 2 does not exist"),
            ("v 0 0 0\nf 1 1\n", 2, "needs 3 vertices"),
            ("v 0 0 0\nf 1 0 1\n", 2, "bad vertex reference '0'"),
            ("v 0 0 0\ncurv 0 1 1\n", 2, "unknown OBJ statement 'curv'"),
        ] {
            let e = parse_obj(Path::new("b.obj"), bad.as_bytes()).unwrap_err();
            assert_eq!(e.line, Some(line), "{bad:?}: {e}");
            assert!(e.to_string().contains(what), "{bad:?}: {e}");
        }
        assert!(parse_obj(Path::new("b.obj"), &[0xff, 0xfe]).is_err());
    }

    #[test]
    fn msh_sizes_must_match() {
        let mut b: Vec<u8> = [3i32, 0, 0, 1].iter().flat_map(|v| v.to_le_bytes()).collect();
        b.extend([0f32, 0., 0., 1., 0., 0., 0., 1., 0.].iter().flat_map(|v| v.to_le_bytes()));
        b.extend([0i32, 1, 2].iter().flat_map(|v| v.to_le_bytes()));
        let m = parse_msh(Path::new("m.msh"), &b).expect("parse");
        assert_eq!((m.points.len(), m.triangles.clone()), (3, vec![[0, 1, 2]]));
        let e = parse_msh(Path::new("m.msh"), &b[..b.len() - 1]).unwrap_err();
        assert!(e.to_string().contains("do not match the file size"), "{e}");
        let n = b.len();
        b[n - 4..].copy_from_slice(&7i32.to_le_bytes());
        assert!(parse_msh(Path::new("m.msh"), &b).unwrap_err().to_string().contains("names vertex 7"));
    }

    #[test]
    fn files_dae_parts_and_package_paths() {
        let d = scratch("files");
        let pkg = d.join("packages").join("demo_pkg").join("meshes");
        std::fs::create_dir_all(pkg.join("part.dae.parts")).expect("mkdir");
        std::fs::write(pkg.join("t.stl"), binary_stl(&TETRA)).expect("write");
        std::fs::write(pkg.join("part.dae"), "<COLLADA/>").expect("write");
        std::fs::write(pkg.join("part.dae.parts").join("0.obj"), "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").expect("w");
        std::fs::write(pkg.join("part.dae.parts").join("1.obj"), "v 0 0 2\nv 1 0 2\nv 0 1 2\nf 1 2 3\n").expect("w");
        std::fs::write(pkg.join("part.dae.parts").join("parts.txt"), "0.obj 1 0 0 1\n1.obj 0 1 0 1\n").expect("w");
        let urdf = d.join("robot").join("r.urdf");
        std::fs::create_dir_all(urdf.parent().expect("parent")).expect("mkdir");
        let search = package_search_path(&urdf);
        assert!(search.contains(&d.join("packages")), "{search:?}");
        let stl = resolve("package://demo_pkg/meshes/t.stl", &urdf, &search).expect("resolve");
        assert_eq!(read_mesh(&stl).expect("read").points.len(), 4);
        let dae = resolve("package://demo_pkg/meshes/part.dae", &urdf, &search).expect("resolve");
        let m = read_mesh(&dae).expect("read");
        assert_eq!((m.points.len(), m.triangles.clone()), (6, vec![[0, 1, 2], [3, 4, 5]]));
        assert!(resolve("../packages/demo_pkg/meshes/t.stl", &urdf, &search).is_ok(), "relative to the URDF");
        let e = resolve("package://nope/x.stl", &urdf, &search).unwrap_err();
        assert!(e.contains("no package 'nope'"), "{e}");
        std::fs::remove_file(pkg.join("part.dae.parts").join("parts.txt")).expect("rm");
        let e = read_mesh(&dae).unwrap_err().to_string();
        assert!(e.contains("COLLADA") && e.contains("robots/assets.py convert"), "{e}");
        std::fs::write(pkg.join("t.ply"), "ply").expect("w");
        assert!(read_mesh(&pkg.join("t.ply")).unwrap_err().to_string().contains("unknown mesh format 'ply'"));
        std::fs::write(pkg.join("empty.obj"), "# nothing\n").expect("w");
        assert!(read_mesh(&pkg.join("empty.obj")).unwrap_err().to_string().contains("no vertices"));
        let _ = std::fs::remove_dir_all(&d);
    }

    /// SplitMix64 in [0, 1).
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        }
        fn point(&mut self, scale: [f64; 3]) -> Point3<f64> {
            Point3::new(scale[0] * (self.next() - 0.5), scale[1] * (self.next() - 0.5), scale[2] * (self.next() - 0.5))
        }
    }

    /// How far `p` is outside the union of `caps` (negative: inside).
    fn outside(caps: &[Capsule], p: &Point3<f64>) -> f64 {
        caps.iter().map(|c| c.axis_distance(p) - c.radius).fold(f64::INFINITY, f64::min)
    }

    /// Every vertex, and points spread over every triangle, lie inside the capsules.
    fn assert_contains(mesh: &Mesh, caps: &[Capsule], what: &str) {
        for p in &mesh.points {
            assert!(outside(caps, p) <= 0.0, "{what}: vertex {p:?} outside by {}", outside(caps, p));
        }
        for t in &mesh.triangles {
            let [a, b, c] = t.map(|i| mesh.points[i as usize]);
            for (u, v) in [(0.2, 0.3), (0.5, 0.5), (0.0, 0.5), (0.9, 0.05), (1.0 / 3.0, 1.0 / 3.0)] {
                let p = a + (b - a) * u + (c - a) * v;
                assert!(outside(caps, &p) <= 1e-9, "{what}: triangle point {p:?} outside by {}", outside(caps, &p));
            }
        }
    }

    #[test]
    fn one_capsule_holds_every_point_and_fits_a_cylinder() {
        let mut rng = Rng(3);
        for (k, scale) in [[0.1, 0.1, 0.4], [0.3, 0.05, 0.05], [0.2, 0.2, 0.2], [1.0, 0.001, 0.5]].iter().enumerate() {
            // Rotated and shifted point clouds.
            let rot = nalgebra::UnitQuaternion::from_euler_angles(0.3 * k as f64, 1.1, -0.4);
            let pts: Vec<Point3<f64>> =
                (0..500).map(|_| rot * rng.point(*scale) + Vector3::new(0.5, -0.2, 0.1 * k as f64)).collect();
            let c = bounding_capsule(&pts).expect("capsule");
            assert!(pts.iter().all(|p| c.axis_distance(p) <= c.radius), "cloud {k}");
        }
        // Points on a cylinder of radius 0.05 and length 0.3 about a tilted axis: the capsule's
        // radius is the cylinder's (the smallest enclosing circle), its axis the cylinder's.
        let axis = Vector3::new(1.0, 2.0, 0.5).normalize();
        let u = axis.cross(&Vector3::z()).normalize();
        let v = axis.cross(&u);
        let pts: Vec<Point3<f64>> = (0..400)
            .map(|i| {
                let (a, s) = (f64::from(i) * 0.7, rng.next() - 0.5);
                Point3::from(axis * 0.3 * s + (u * a.cos() + v * a.sin()) * 0.05)
            })
            .collect();
        // Along the cylinder's axis the radius is the cylinder's (the smallest enclosing circle)
        // and the segment as long as the caps allow.
        let c = capsule_along(&pts, &axis);
        assert!((c.radius - 0.05).abs() < 1e-4, "{c:?}");
        assert!((c.b - c.a).norm() < 0.3 + 1e-3, "{c:?}");
        // The least-volume candidate may tilt a little (a wider capsule with shorter caps).
        let best = bounding_capsule(&pts).expect("capsule");
        assert!(best.volume() <= c.volume() * 1.01 && best.radius < 0.055, "{best:?}");
        assert!((best.b - best.a).normalize().dot(&axis).abs() > 0.99, "{best:?}");
        assert!(bounding_capsule(&[]).is_none());
        assert!(bounding_capsule(&[Point3::new(f64::NAN, 0.0, 0.0)]).is_none());
        let one = bounding_capsule(&[Point3::new(1.0, 2.0, 3.0)]).expect("a sphere");
        assert!(one.a == one.b && one.radius <= 2.0 * F32_SLACK_M);
    }

    /// An L made of two boxes, as triangles.
    fn box_mesh(m: &mut Mesh, lo: [f64; 3], hi: [f64; 3]) {
        let base = m.points.len() as u32;
        for k in 0..8 {
            m.points.push(Point3::new(
                if k & 1 == 0 { lo[0] } else { hi[0] },
                if k & 2 == 0 { lo[1] } else { hi[1] },
                if k & 4 == 0 { lo[2] } else { hi[2] },
            ));
        }
        for f in [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]] {
            m.triangles.push([base + f[0], base + f[1], base + f[2]]);
            m.triangles.push([base + f[0], base + f[2], base + f[3]]);
        }
    }

    #[test]
    fn several_capsules_hold_every_triangle() {
        let mut l = Mesh::default();
        box_mesh(&mut l, [0.0, 0.0, 0.0], [0.05, 0.05, 0.4]);
        box_mesh(&mut l, [0.0, 0.0, 0.35], [0.3, 0.05, 0.4]);
        let one = bounding_capsules(&l, 1).expect("one");
        let three = bounding_capsules(&l, 3).expect("three");
        assert_eq!(one.len(), 1);
        assert!(three.len() >= 2, "an L is cut: {three:?}");
        let vol = |c: &[Capsule]| c.iter().map(Capsule::volume).sum::<f64>();
        assert!(vol(&three) < 0.5 * vol(&one), "{} vs {}", vol(&three), vol(&one));
        assert_contains(&l, &three, "L");
        // Random triangle soups, cut or not.
        let mut rng = Rng(9);
        for k in 0..20 {
            let mut m = Mesh::default();
            for _ in 0..30 {
                m.points.push(rng.point([0.4, 0.1 + 0.02 * f64::from(k), 0.2]));
            }
            for _ in 0..40 {
                let i = |r: &mut Rng| (r.next() * 30.0) as u32;
                m.triangles.push([i(&mut rng), i(&mut rng), i(&mut rng)]);
            }
            let caps = bounding_capsules(&m, 3).expect("caps");
            assert!(!caps.is_empty() && caps.len() <= 3);
            assert_contains(&m, &caps, &format!("soup {k}"));
        }
    }

    /// The shipped third-party Panda's collision meshes (skipped when robots/packages/ is not set
    /// up): every vertex and triangle inside the capsules.
    #[test]
    fn third_party_panda_meshes_are_held() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../robots/packages/example-robot-data/robots/panda_description/meshes/collision");
        if !dir.is_dir() {
            eprintln!("skipped: {} missing (scripts/setup-venv.sh)", dir.display());
            return;
        }
        for n in ["link0", "link1", "link2", "link3", "link4", "link5", "link6", "link7", "hand", "finger"] {
            let m = read_mesh(&dir.join(format!("{n}.stl"))).expect("read");
            let caps = bounding_capsules(&m, MAX_CAPSULES_PER_MESH).expect("caps");
            assert_contains(&m, &caps, n);
        }
    }
}
