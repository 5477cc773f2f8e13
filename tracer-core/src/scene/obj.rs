//! The OBJ subset of conventions.md §4, parsed by hand: the course's rules (format detected
//! from the first face, quads split (0,1,2)+(2,3,0), vertices de-duplicated by index triple,
//! no relative indices) differ from what general OBJ crates do, and errors need line:column.

use std::collections::HashMap;

use glam::{DVec2, DVec3};

use super::SceneError;

/// A triangle mesh in its own local space, one entry per de-duplicated vertex.
#[derive(Clone, Debug, Default)]
pub struct MeshData {
    pub positions: Vec<DVec3>,
    /// Unit normals; from the file, or smooth normals computed from the faces. A vertex all of
    /// whose faces are degenerate keeps a zero normal (shading then uses the geometric one).
    pub normals: Vec<DVec3>,
    pub tex_coords: Vec<DVec2>,
    pub triangles: Vec<[u32; 3]>,
    pub has_normals: bool,
    pub has_tex_coords: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum FaceFormat {
    Position,
    PositionTex,
    PositionNormal,
    PositionTexNormal,
}

impl FaceFormat {
    fn detect(token: &str) -> Self {
        match token.split('/').collect::<Vec<_>>().as_slice() {
            [_] => Self::Position,
            [_, _] => Self::PositionTex,
            [_, "", _] => Self::PositionNormal,
            _ => Self::PositionTexNormal,
        }
    }
}

/// Parses OBJ text; `file` names it in errors.
pub fn parse_obj(text: &str, file: &str) -> Result<MeshData, SceneError> {
    parse_obj_with_limit(text, file, u64::MAX, u64::MAX)
}

/// Parses OBJ text, stopping at the face that takes the mesh past `max_triangles`: that face's
/// `file:line:column` is reported as passing `max_primitives` (whose whole value, `limit`, the
/// message quotes; `max_triangles` is what the scene had left of it).
pub fn parse_obj_with_limit(
    text: &str,
    file: &str,
    max_triangles: u64,
    limit: u64,
) -> Result<MeshData, SceneError> {
    let used_elsewhere = limit.saturating_sub(max_triangles);
    let mut raw_positions: Vec<DVec3> = Vec::new();
    let mut raw_normals: Vec<DVec3> = Vec::new();
    let mut raw_tex: Vec<DVec2> = Vec::new();
    let mut mesh = MeshData::default();
    let mut format: Option<FaceFormat> = None;
    let mut vertex_ids = VertexIds::default();
    let mut face: Vec<u32> = Vec::with_capacity(4);

    for (line_index, line) in text.lines().enumerate() {
        let line_no = line_index as u32 + 1;
        let err = |token: &str, message: String| {
            // Column of `token` within the line (1-based); tokens are slices of `line`.
            let column = token.as_ptr() as usize - line.as_ptr() as usize + 1;
            SceneError::new(file, line_no, column as u32, message)
        };
        let mut tokens = line.split_ascii_whitespace();
        let Some(kind) = tokens.next() else { continue };
        match kind {
            "v" | "vn" => {
                let p = read_numbers::<3>(&mut tokens, kind, &err, line)?;
                let v = DVec3::from_array(p);
                if kind == "v" {
                    raw_positions.push(v);
                } else {
                    raw_normals.push(v);
                }
            }
            "vt" => {
                let t = read_numbers::<2>(&mut tokens, kind, &err, line)?;
                raw_tex.push(DVec2::from_array(t));
            }
            "f" => {
                face.clear();
                // At most four corners are kept; more are only counted, for the message.
                let (corners, count) = first_of::<4>(tokens);
                if !(3..=4).contains(&count) {
                    return Err(err(
                        kind,
                        format!("a face needs 3 or 4 vertices, this one has {count}"),
                    ));
                }
                let corners = &corners[..count];
                let format = *format.get_or_insert_with(|| FaceFormat::detect(corners[0]));
                for &token in corners {
                    let key = corner_key(
                        token,
                        format,
                        [raw_positions.len(), raw_tex.len(), raw_normals.len()],
                    )
                    .map_err(|m| err(token, m))?;
                    let next_id = mesh.positions.len() as u32;
                    let id = vertex_ids.id(key, next_id);
                    if id == next_id {
                        mesh.positions.push(raw_positions[key.0 as usize]);
                        mesh.tex_coords.push(if key.1 >= 0 {
                            raw_tex[key.1 as usize]
                        } else {
                            DVec2::ZERO
                        });
                        mesh.normals.push(if key.2 >= 0 {
                            raw_normals[key.2 as usize].normalize_or_zero()
                        } else {
                            DVec3::ZERO
                        });
                    }
                    face.push(id);
                }
                let triangles = mesh.triangles.len() as u64 + face.len() as u64 - 2;
                if triangles > max_triangles {
                    let column = kind.as_ptr() as usize - line.as_ptr() as usize + 1;
                    return Err(SceneError::over_limit(
                        file,
                        line_no,
                        column as u32,
                        "max_primitives",
                        used_elsewhere.saturating_add(triangles),
                        limit,
                        "primitives with this mesh's triangles so far",
                    ));
                }
                mesh.triangles.push([face[0], face[1], face[2]]);
                if face.len() == 4 {
                    mesh.triangles.push([face[2], face[3], face[0]]);
                }
            }
            _ => {}
        }
    }
    mesh.has_normals = matches!(
        format,
        Some(FaceFormat::PositionNormal | FaceFormat::PositionTexNormal)
    );
    mesh.has_tex_coords = matches!(
        format,
        Some(FaceFormat::PositionTex | FaceFormat::PositionTexNormal)
    );
    if mesh.triangles.is_empty() {
        return Err(SceneError::new(file, 0, 0, "the mesh has no faces"));
    }
    if !mesh.has_normals {
        mesh.normals = smooth_normals(&mesh.positions, &mesh.triangles);
    }
    Ok(mesh)
}

fn read_numbers<const N: usize>(
    tokens: &mut std::str::SplitAsciiWhitespace<'_>,
    kind: &str,
    err: &impl Fn(&str, String) -> SceneError,
    line: &str,
) -> Result<[f64; N], SceneError> {
    let mut out = [0.0; N];
    for slot in out.iter_mut() {
        let Some(token) = tokens.next() else {
            let end = &line[line.len()..];
            return Err(err(end, format!("'{kind}' needs {N} numbers")));
        };
        match token.parse::<f64>() {
            Ok(v) if v.is_finite() => *slot = v,
            _ => return Err(err(token, format!("'{token}' is not a finite number"))),
        }
    }
    Ok(out)
}

/// The de-duplicated vertex of each (position, tex coord, normal) key (-1 where absent).
/// Most positions are used with one key only (all of the course's meshes'): the first key
/// of each position sits in a table indexed by position, and only later ones are hashed,
/// which made parsing the dragon several times faster than hashing every corner.
#[derive(Default)]
struct VertexIds {
    /// Per position index, the vertex of the first key seen with it (u32::MAX: none yet).
    first: Vec<u32>,
    /// Per vertex, the tex coord and normal of its key.
    rest: Vec<(i64, i64)>,
    /// Keys whose position had been seen with another key first.
    others: HashMap<(i64, i64, i64), u32>,
}

impl VertexIds {
    /// The vertex of `key`, or `next` (recorded as its vertex) where `key` is new; new keys
    /// come with consecutive `next`s from 0.
    fn id(&mut self, key: (i64, i64, i64), next: u32) -> u32 {
        let (position, tex, normal) = key;
        let position = position as usize;
        if position >= self.first.len() {
            self.first.resize(position + 1, u32::MAX);
        }
        let first = self.first[position];
        let id = if first == u32::MAX {
            self.first[position] = next;
            next
        } else if self.rest[first as usize] == (tex, normal) {
            first
        } else {
            *self.others.entry(key).or_insert(next)
        };
        if id == next {
            self.rest.push((tex, normal));
        }
        id
    }
}

/// The first `N` items of `items` and how many there were in all, without allocating (missing
/// ones are empty).
fn first_of<'a, const N: usize>(items: impl Iterator<Item = &'a str>) -> ([&'a str; N], usize) {
    let mut first = [""; N];
    let mut count = 0;
    for item in items {
        if count < N {
            first[count] = item;
        }
        count += 1;
    }
    (first, count)
}

/// Resolves one face corner to its (position, tex coord, normal) key, all 0-based.
fn corner_key(
    token: &str,
    format: FaceFormat,
    counts: [usize; 3],
) -> Result<(i64, i64, i64), String> {
    // Up to three parts are kept; a fourth only makes the count wrong.
    let (parts, count) = first_of::<3>(token.split('/'));
    let expected = match format {
        FaceFormat::Position => 1,
        FaceFormat::PositionTex => 2,
        FaceFormat::PositionNormal | FaceFormat::PositionTexNormal => 3,
    };
    let shape_ok = count == expected
        && match format {
            FaceFormat::PositionNormal => parts[1].is_empty(),
            FaceFormat::PositionTexNormal => !parts[1].is_empty(),
            _ => true,
        };
    if !shape_ok {
        return Err(format!(
            "face vertex '{token}' does not match the file's face format ({format:?}, taken from its first face)"
        ));
    }
    let index = |text: &str, count: usize, what: &str| -> Result<i64, String> {
        let value: i64 = text
            .parse()
            .map_err(|_| format!("'{text}' is not a valid {what} index"))?;
        if value < 1 {
            return Err(format!(
                "{what} index {value} is not supported (indices are 1-based; relative indices are not allowed)"
            ));
        }
        if value as usize > count {
            return Err(format!(
                "{what} index {value} is out of range: only {count} defined so far"
            ));
        }
        Ok(value - 1)
    };
    let position = index(parts[0], counts[0], "position")?;
    let tex = match format {
        FaceFormat::PositionTex | FaceFormat::PositionTexNormal => {
            index(parts[1], counts[1], "tex coord")?
        }
        _ => -1,
    };
    let normal = match format {
        FaceFormat::PositionNormal | FaceFormat::PositionTexNormal => {
            index(parts[2], counts[2], "normal")?
        }
        _ => -1,
    };
    Ok((position, tex, normal))
}

/// The course's smooth normals: per vertex, the normalised sum of the unit normals of the
/// faces that use it (equal weights). Degenerate faces are skipped.
pub fn smooth_normals(positions: &[DVec3], triangles: &[[u32; 3]]) -> Vec<DVec3> {
    let mut sums = vec![DVec3::ZERO; positions.len()];
    for tri in triangles {
        let [a, b, c] = tri.map(|i| positions[i as usize]);
        let n = (b - a).cross(c - a).normalize_or_zero();
        if n != DVec3::ZERO {
            for &i in tri {
                sums[i as usize] += n;
            }
        }
    }
    sums.into_iter().map(DVec3::normalize_or_zero).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quads_split_and_vertices_dedup_by_triple() {
        let text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 2\n\
                    f 1/1/1 2/2/1 3/3/1 4/4/1\nf 1/1/1 3/3/1 4/4/1\n";
        let mesh = parse_obj(text, "q.obj").unwrap();
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [2, 3, 0], [0, 2, 3]]);
        assert_eq!(mesh.positions.len(), 4);
        assert!(mesh.has_normals && mesh.has_tex_coords);
        assert_eq!(mesh.normals[0], DVec3::Z, "file normals are normalised");
        assert_eq!(mesh.tex_coords[2], DVec2::new(1.0, 1.0));
    }

    #[test]
    fn a_position_with_several_keys_makes_a_vertex_per_key_in_first_seen_order() {
        // Position 1 with normals 1, 2, then 1 again, and position 2 with one key: the
        // vertices are numbered as their keys first appear, whichever way they are found.
        let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nvn 0 1 0\n\
                    f 1//1 2//1 3//1\nf 1//2 3//1 2//1\nf 3//2 1//2 1//1\nf 2//1 1//1 3//2\n";
        let mesh = parse_obj(text, "k.obj").unwrap();
        assert_eq!(
            mesh.triangles,
            vec![[0, 1, 2], [3, 2, 1], [4, 3, 0], [1, 0, 4]]
        );
        assert_eq!(mesh.positions[3], DVec3::ZERO);
        assert_eq!(mesh.normals[3], DVec3::Y);
        assert_eq!(mesh.positions[4], DVec3::Y);
        assert_eq!(mesh.normals[4], DVec3::Y);
    }

    #[test]
    fn all_four_face_forms() {
        let head = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n";
        for (face, normals, tex) in [
            ("f 1 2 3", false, false),
            ("f 1/1 2/1 3/1", false, true),
            ("f 1//1 2//1 3//1", true, false),
            ("f 1/1/1 2/1/1 3/1/1", true, true),
        ] {
            let mesh = parse_obj(&format!("{head}{face}\n"), "f.obj").unwrap();
            assert_eq!(
                (mesh.has_normals, mesh.has_tex_coords),
                (normals, tex),
                "{face}"
            );
            assert_eq!(mesh.triangles.len(), 1);
            assert!((mesh.normals[0] - DVec3::Z).length() < 1e-12, "{face}");
        }
    }

    #[test]
    fn smooth_normals_weight_faces_equally() {
        // A fan of one large and one tiny face meeting at vertex 0 at right angles.
        let positions = vec![
            DVec3::ZERO,
            DVec3::new(100.0, 0.0, 0.0),
            DVec3::new(0.0, 100.0, 0.0),
            DVec3::new(0.0, 0.0, 0.01),
        ];
        let normals = smooth_normals(&positions, &[[0, 1, 2], [0, 3, 1]]);
        let expected = (DVec3::Z + DVec3::Y).normalize();
        assert!((normals[0] - expected).length() < 1e-12);
        assert_eq!(normals[2], DVec3::Z);
    }

    #[test]
    fn bad_indices_and_counts_report_line_and_column() {
        let head = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
        let e = parse_obj(&format!("{head}f 1 2 4\n"), "m.obj").unwrap_err();
        assert_eq!((e.line, e.column), (4, 7), "{e}");
        assert!(e.message.contains("out of range"));
        let e = parse_obj(&format!("{head}f -1 2 3\n"), "m.obj").unwrap_err();
        assert_eq!((e.line, e.column), (4, 3), "{e}");
        let e = parse_obj(&format!("{head}f 1 2\n"), "m.obj").unwrap_err();
        assert!(e.message.contains("3 or 4"), "{e}");
        let e = parse_obj(&format!("{head}f 1 2 3 1 2\n"), "m.obj").unwrap_err();
        assert!(e.message.contains("this one has 5"), "{e}");
        let e = parse_obj(&format!("{head}vn 0 0 1\nf 1//1//1 2//1 3//1\n"), "m.obj").unwrap_err();
        assert_eq!((e.line, e.column), (5, 3), "{e}");
        assert!(e.message.contains("face format"), "{e}");
        let e = parse_obj("v 0 x 0\n", "m.obj").unwrap_err();
        assert_eq!((e.line, e.column), (1, 5), "{e}");
        let e = parse_obj("v 0 0\n", "m.obj").unwrap_err();
        assert!(e.message.contains("needs 3"), "{e}");
        let e = parse_obj(&format!("{head}f 1 2 3\nf 1/1 2/1 3/1\n"), "m.obj").unwrap_err();
        assert!(e.message.contains("face format"), "{e}");
        let e = parse_obj("v nan 0 0\n", "m.obj").unwrap_err();
        assert!(e.message.contains("finite"), "{e}");
    }

    #[test]
    fn the_triangle_budget_stops_at_the_face_that_passes_it() {
        let text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 2 3 4\n";
        assert_eq!(
            parse_obj_with_limit(text, "m.obj", 3, 3)
                .unwrap()
                .triangles
                .len(),
            3
        );
        let e = parse_obj_with_limit(text, "m.obj", 2, 10).unwrap_err();
        assert_eq!(
            (e.line, e.column, e.limit()),
            (6, 1, Some("max_primitives")),
            "{e}"
        );
        assert!(
            e.message.contains("11 is over") && e.message.contains("= 10"),
            "{e}"
        );
    }
}
