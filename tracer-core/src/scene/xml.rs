//! A small element tree over quick-xml that remembers where each element starts, so every
//! later error can say `file:line:column`.

use quick_xml::events::{BytesStart, Event};
use quick_xml::Reader;

use super::SceneError;

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
}

impl<'a> LineIndex<'a> {
    fn new(text: &'a str) -> Self {
        let mut line_starts = vec![0];
        line_starts.extend(text.match_indices('\n').map(|(i, _)| i + 1));
        Self { text, line_starts }
    }

    fn pos(&self, offset: usize) -> Pos {
        let offset = offset.min(self.text.len());
        let line = self.line_starts.partition_point(|&s| s <= offset) - 1;
        let start = self.line_starts[line];
        let mut column = 0u32;
        for ch in self.text[start..offset].chars() {
            column = if ch == '\t' {
                (column / 4 + 1) * 4
            } else {
                column + 1
            };
        }
        Pos {
            line: line as u32 + 1,
            column: column + 1,
        }
    }
}

/// Parses `text` and returns the document's first root element.
pub fn parse_document(text: &str, file: &str) -> Result<Element, SceneError> {
    let index = LineIndex::new(text);
    let error_at = |offset: u64, message: String| {
        let pos = index.pos(offset as usize);
        SceneError::new(file, pos.line, pos.column, message)
    };
    let mut reader = Reader::from_str(text);
    reader.config_mut().check_end_names = true;
    let mut stack: Vec<Element> = Vec::new();
    let mut root: Option<Element> = None;
    loop {
        let start = reader.buffer_position();
        let event = reader
            .read_event()
            .map_err(|e| error_at(reader.error_position(), format!("XML parse error: {e}")))?;
        match event {
            Event::Start(tag) => {
                let element = open_element(&tag, index.pos(start as usize), &error_at, start)?;
                stack.push(element);
            }
            Event::Empty(tag) => {
                let element = open_element(&tag, index.pos(start as usize), &error_at, start)?;
                close_element(element, &mut stack, &mut root);
            }
            Event::End(_) => {
                let element = stack.pop().expect("quick-xml checks that end tags match");
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

    #[test]
    fn positions_point_at_the_opening_bracket() {
        let doc = parse_document("<scene>\n  <a v=\"1\"/>\n\t<b>\n\t</b>\n</scene>", "f").unwrap();
        assert_eq!(doc.pos, Pos { line: 1, column: 1 });
        assert_eq!(doc.children[0].pos, Pos { line: 2, column: 3 });
        // A tab advances to the next multiple of 4, as TinyXML counts.
        assert_eq!(doc.children[1].pos, Pos { line: 3, column: 5 });
        assert_eq!(doc.children[0].attr("v"), Some("1"));
    }

    #[test]
    fn malformed_xml_is_an_error_with_a_position() {
        let err = parse_document("<scene>\n  <a>\n</scene>", "bad.scene").unwrap_err();
        assert_eq!(err.file, "bad.scene");
        assert_eq!(err.line, 3, "{err}");
        let err = parse_document("<scene>\n  <a>", "bad.scene").unwrap_err();
        assert!(err.message.contains("never closed"), "{err}");
        assert!(parse_document("   ", "empty")
            .unwrap_err()
            .message
            .contains("no root"));
    }
}
