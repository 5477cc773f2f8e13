//! A small element tree over quick-xml that remembers where each element starts, so every
//! later error can say `file:line:column`.
//!
//! The tree is bounded before it is built: elements nest at most [`MAX_DEPTH`] deep (so no
//! walk over the tree, dropping it included, recurses deeper than that), the document holds at
//! most [`LoadLimits::max_elements`] elements, and spheres, triangles and models are counted against
//! `max_primitives` as they open.

use std::cell::Cell;

use quick_xml::events::{BytesStart, Event};
use quick_xml::Reader;

use super::{LoadLimits, SceneError};

/// How deep elements may nest, the root being depth 1. Course scenes nest 3 deep (a keyframe's
/// position inside a triangle is the deepest extension, at 4).
pub const MAX_DEPTH: usize = 32;

/// The byte-order mark some editors write at the start of a UTF-8 file.
const BOM: char = '\u{FEFF}';

/// 1-based line and column of an element's opening `<`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Pos {
    pub line: u32,
    pub column: u32,
}

#[derive(Debug)]
pub struct Element {
    pub name: String,
    pub attrs: Vec<(String, String)>,
    pub children: Vec<Element>,
    pub pos: Pos,
}

impl Element {
    pub fn attr(&self, name: &str) -> Option<&str> {
        self.attrs
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }

    pub fn children_named<'a>(&'a self, name: &'a str) -> impl Iterator<Item = &'a Element> + 'a {
        self.children.iter().filter(move |c| c.name == name)
    }
}

/// Maps byte offsets to line and column, with tab stops every 4 columns as TinyXML counts them.
struct LineIndex<'a> {
    text: &'a str,
    line_starts: Vec<usize>,
    /// The last offset mapped, its line index and 0-based column: the parser asks for offsets
    /// in increasing order, so each column is counted on from the previous one, not from the
    /// line's start (which made a file on one line cost quadratic time).
    cursor: Cell<(usize, usize, u32)>,
}

impl<'a> LineIndex<'a> {
    fn new(text: &'a str) -> Self {
        let mut line_starts = vec![0];
        line_starts.extend(text.match_indices('\n').map(|(i, _)| i + 1));
        Self {
            text,
            line_starts,
            cursor: Cell::new((0, 0, 0)),
        }
    }

    /// Total over all offsets: one past the end clamps to the end, one inside a multi-byte
    /// character counts as that character.
    fn pos(&self, offset: usize) -> Pos {
        let mut offset = offset.min(self.text.len());
        while !self.text.is_char_boundary(offset) {
            offset -= 1;
        }
        let line = self.line_starts.partition_point(|&s| s <= offset) - 1;
        let (cursor_offset, cursor_line, cursor_column) = self.cursor.get();
        let (from, mut column) = if cursor_line == line && cursor_offset <= offset {
            (cursor_offset, cursor_column)
        } else {
            (self.line_starts[line], 0)
        };
        for ch in self.text[from..offset].chars() {
            column = if ch == '\t' {
                (column / 4).saturating_add(1).saturating_mul(4)
            } else {
                column.saturating_add(1)
            };
        }
        self.cursor.set((offset, line, column));
        Pos {
            line: line as u32 + 1,
            column: column.saturating_add(1),
        }
    }
}

/// Parses `text` and returns the document's first root element. A leading byte-order mark is
/// skipped; positions count from the character after it.
pub fn parse_document(text: &str, file: &str, limits: &LoadLimits) -> Result<Element, SceneError> {
    let text = text.strip_prefix(BOM).unwrap_or(text);
    let index = LineIndex::new(text);
    let error_at = |offset: u64, message: String| {
        let pos = index.pos(offset as usize);
        SceneError::new(file, pos.line, pos.column, message)
    };
    let mut reader = Reader::from_str(text);
    reader.config_mut().check_end_names = true;
    let mut stack: Vec<Element> = Vec::new();
    let mut root: Option<Element> = None;
    let mut counts = Counts::default();
    loop {
        let start = reader.buffer_position();
        let event = reader
            .read_event()
            .map_err(|e| error_at(reader.error_position(), format!("XML parse error: {e}")))?;
        match event {
            Event::Start(tag) => {
                let element = open_element(&tag, index.pos(start as usize), &error_at, start)?;
                counts.admit(&element, &stack, root.is_none(), limits, file)?;
                stack.push(element);
            }
            Event::Empty(tag) => {
                let element = open_element(&tag, index.pos(start as usize), &error_at, start)?;
                counts.admit(&element, &stack, root.is_none(), limits, file)?;
                close_element(element, &mut stack, &mut root);
            }
            Event::End(tag) => {
                // quick-xml checks that end tags match their start tags; an end tag with no
                // open element is still an error here rather than a panic.
                let Some(element) = stack.pop() else {
                    let name = tag.name().into_inner().to_string();
                    return Err(error_at(
                        start,
                        format!("XML parse error: </{name}> closes no element"),
                    ));
                };
                close_element(element, &mut stack, &mut root);
            }
            Event::Eof => {
                if let Some(open) = stack.last() {
                    return Err(SceneError::new(
                        file,
                        open.pos.line,
                        open.pos.column,
                        format!("XML parse error: <{}> is never closed", open.name),
                    ));
                }
                break;
            }
            _ => {}
        }
    }
    root.ok_or_else(|| SceneError::new(file, 1, 1, "the document has no root element"))
}

/// What the document has opened so far, checked against the limits as each element opens.
#[derive(Default)]
struct Counts {
    elements: u64,
    primitives: u64,
}

impl Counts {
    /// Counts `element`, about to become a child of `stack`'s top, and refuses it when it nests
    /// too deep or passes a budget. `first_root` says whether `stack` is inside the document's
    /// first root (the only one that is read).
    fn admit(
        &mut self,
        element: &Element,
        stack: &[Element],
        first_root: bool,
        limits: &LoadLimits,
        file: &str,
    ) -> Result<(), SceneError> {
        let at = element.pos;
        if stack.len() >= MAX_DEPTH {
            return Err(SceneError::new(
                file,
                at.line,
                at.column,
                format!(
                    "<{}> nests {} elements deep; scene files may nest at most {MAX_DEPTH}",
                    element.name,
                    stack.len() + 1
                ),
            ));
        }
        self.elements += 1;
        if self.elements > limits.max_elements() {
            return Err(SceneError::over_element_bound(
                file,
                at.line,
                at.column,
                limits,
                self.elements,
                "XML elements",
            ));
        }
        // A model is one instance in the top-level BVH; its mesh's triangles are counted once
        // per mesh file when the OBJ is read.
        let is_primitive = matches!(element.name.as_str(), "sphere" | "triangle" | "model");
        if is_primitive && first_root && stack.len() == 1 {
            self.primitives += 1;
            if self.primitives > limits.max_primitives {
                return Err(SceneError::over_limit(
                    file,
                    at.line,
                    at.column,
                    "max_primitives",
                    self.primitives,
                    limits.max_primitives,
                    "spheres, triangles and models",
                ));
            }
        }
        Ok(())
    }
}

fn open_element(
    tag: &BytesStart,
    pos: Pos,
    error_at: &impl Fn(u64, String) -> SceneError,
    offset: u64,
) -> Result<Element, SceneError> {
    let name = tag.name().into_inner().to_string();
    let mut attrs = Vec::new();
    for attr in tag.attributes() {
        let attr =
            attr.map_err(|e| error_at(offset, format!("XML parse error in <{name}>: {e}")))?;
        let key = attr.key.into_inner().to_string();
        let value = attr
            .normalized_value(quick_xml::XmlVersion::Implicit1_0)
            .map_err(|e| error_at(offset, format!("XML parse error in <{name}>: {e}")))?
            .into_owned();
        attrs.push((key, value));
    }
    Ok(Element {
        name,
        attrs,
        children: Vec::new(),
        pos,
    })
}

fn close_element(element: Element, stack: &mut [Element], root: &mut Option<Element>) {
    match stack.last_mut() {
        Some(parent) => parent.children.push(element),
        // TinyXML's root is the first top-level element; later ones are ignored.
        None if root.is_none() => *root = Some(element),
        None => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str, file: &str) -> Result<Element, SceneError> {
        parse_document(text, file, &LoadLimits::UNLIMITED)
    }

    #[test]
    fn positions_point_at_the_opening_bracket() {
        let doc = parse("<scene>\n  <a v=\"1\"/>\n\t<b>\n\t</b>\n</scene>", "f").unwrap();
        assert_eq!(doc.pos, Pos { line: 1, column: 1 });
        assert_eq!(doc.children[0].pos, Pos { line: 2, column: 3 });
        // A tab advances to the next multiple of 4, as TinyXML counts.
        assert_eq!(doc.children[1].pos, Pos { line: 3, column: 5 });
        assert_eq!(doc.children[0].attr("v"), Some("1"));
    }

    #[test]
    fn malformed_xml_is_an_error_with_a_position() {
        let err = parse("<scene>\n  <a>\n</scene>", "bad.scene").unwrap_err();
        assert_eq!(err.file, "bad.scene");
        assert_eq!(err.line, 3, "{err}");
        let err = parse("<scene>\n  <a>", "bad.scene").unwrap_err();
        assert!(err.message.contains("never closed"), "{err}");
        assert!(parse("   ", "empty")
            .unwrap_err()
            .message
            .contains("no root"));
    }

    #[test]
    fn every_offset_maps_to_a_position() {
        let text = "é\n\t€x\n";
        let index = LineIndex::new(text);
        for offset in 0..=text.len() + 2 {
            let pos = index.pos(offset);
            assert!(pos.line >= 1 && pos.column >= 1, "{offset}: {pos:?}");
        }
        // Inside 'é' counts as 'é' itself; after the tab and '€', column 6.
        assert_eq!(index.pos(1), Pos { line: 1, column: 1 });
        assert_eq!(
            index.pos(text.find('x').unwrap()),
            Pos { line: 2, column: 6 }
        );
    }

    #[test]
    fn counting_on_from_the_last_position_agrees_with_counting_afresh() {
        let text = "a\tb\té€\t\tc\n\t d😀\te\n\nxyz";
        let ascending = LineIndex::new(text);
        let descending = LineIndex::new(text);
        let offsets: Vec<usize> = (0..=text.len() + 1).collect();
        for (&up, &down) in offsets.iter().zip(offsets.iter().rev()) {
            assert_eq!(ascending.pos(up), LineIndex::new(text).pos(up), "{up}");
            assert_eq!(
                descending.pos(down),
                LineIndex::new(text).pos(down),
                "{down}"
            );
        }
    }

    #[test]
    fn a_byte_order_mark_is_skipped() {
        let doc = parse("\u{FEFF}<scene>\n  <a/>\n</scene>", "f").unwrap();
        assert_eq!(doc.pos, Pos { line: 1, column: 1 });
        assert_eq!(doc.children[0].pos, Pos { line: 2, column: 3 });
        assert!(parse("\u{FEFF}\n<", "f").is_err());
    }

    #[test]
    fn nesting_is_bounded() {
        let nested = |depth: usize| "<a>".repeat(depth) + &"</a>".repeat(depth);
        assert!(parse(&nested(MAX_DEPTH), "f").is_ok());
        let err = parse(&nested(MAX_DEPTH + 1), "f").unwrap_err();
        assert_eq!(
            (err.line, err.column),
            (1, 3 * MAX_DEPTH as u32 + 1),
            "{err}"
        );
        assert!(err.message.contains("at most 32"), "{err}");
        let err = parse(&format!("{}<b/>", "<a>".repeat(MAX_DEPTH)), "f").unwrap_err();
        assert!(err.message.contains("<b>"), "{err}");
    }

    #[test]
    fn primitives_and_elements_are_counted_as_they_open() {
        let limits = LoadLimits {
            max_primitives: 2,
            ..LoadLimits::UNLIMITED
        };
        let two = "<s><sphere/><triangle><sphere/></triangle></s><sphere/>";
        assert!(
            parse_document(two, "f", &limits).is_ok(),
            "nested and later roots do not count"
        );
        let err =
            parse_document("<s><sphere/><triangle/>\n<sphere/></s>", "f", &limits).unwrap_err();
        assert_eq!(
            (err.line, err.column, err.limit()),
            (2, 1, Some("max_primitives"))
        );
        assert!(
            err.message.contains("3 is over") && err.message.contains("= 2"),
            "{err}"
        );
        let none = LoadLimits {
            max_primitives: 0,
            ..LoadLimits::UNLIMITED
        };
        let many = format!(
            "<s>{}</s>",
            "<m/>".repeat(LoadLimits::ELEMENT_ALLOWANCE as usize)
        );
        let err = parse_document(&many, "f", &none).unwrap_err();
        assert_eq!(err.limit(), Some("max_primitives"), "{err}");
        assert!(err.message.contains("XML elements"), "{err}");
    }

    #[test]
    fn a_stray_end_tag_is_an_error() {
        assert!(parse("</a>", "f").is_err());
        assert!(parse("<a></a></b>", "f").is_err());
    }
}
