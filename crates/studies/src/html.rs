//! A report as one self-contained HTML page: the markdown rendered (tables included), every
//! SVG plot it links put inline, so the page opens in a browser from anywhere, mailed or
//! moved, with nothing beside it.

use std::path::Path;

use pulldown_cmark::{Event, Options, Parser, Tag, TagEnd, html};

use crate::error::{RenderError, Result};

/// The page's style: readable tables and plots that fit the window.
const STYLE: &str = "body{font-family:system-ui,sans-serif;max-width:70rem;margin:2rem auto;padding:0 1rem;line-height:1.45;color:#222}\
table{border-collapse:collapse;margin:1rem 0;font-size:.9rem;display:block;overflow-x:auto}\
th,td{border:1px solid #ccc;padding:.25rem .5rem;text-align:right}th{background:#f3f3f3}\
td:first-child,th:first-child{text-align:left}code{background:#f3f3f3;padding:0 .2rem}\
figure{margin:1rem 0}figure svg{max-width:100%;height:auto}figcaption{font-size:.9rem;color:#555}";

/// The HTML page of `markdown`, whose image links are relative to `dir`: SVG images are put
/// inline (their files read from `dir`), other images keep their links.
///
/// # Errors
/// [`RenderError::Io`] when a linked SVG cannot be read.
pub fn page(title: &str, markdown: &str, dir: &Path) -> Result<String> {
    let mut events = Vec::new();
    let mut image: Option<(String, String)> = None;
    for event in Parser::new_ext(markdown, Options::ENABLE_TABLES) {
        match (&mut image, event) {
            (None, Event::Start(Tag::Image { dest_url, .. })) if dest_url.ends_with(".svg") => {
                image = Some((dest_url.to_string(), String::new()));
            }
            (Some((_, alt)), Event::Text(t)) => alt.push_str(&t),
            (Some(_), Event::End(TagEnd::Image)) => {
                let (file, alt) = image.take().expect("inside an image");
                events.push(Event::Html(inline_svg(dir, &file, &alt)?.into()));
            }
            (Some(_), _) => {}
            (None, event) => events.push(event),
        }
    }
    let mut body = String::new();
    html::push_html(&mut body, events.into_iter());
    Ok(format!(
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>{}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n{body}</body>\n</html>\n",
        escape(title)
    ))
}

/// The SVG file `dir/file` as a figure captioned `alt` (its XML declaration dropped).
fn inline_svg(dir: &Path, file: &str, alt: &str) -> Result<String> {
    let path = dir.join(file);
    let svg = std::fs::read_to_string(&path).map_err(|source| RenderError::Io { path, source })?;
    let start = svg.find("<svg").unwrap_or(0);
    Ok(format!(
        "<figure>{}<figcaption>{}</figcaption></figure>\n",
        &svg[start..],
        escape(alt)
    ))
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn svg_images_go_inline_and_tables_render() {
        let dir = tempfile::tempdir().unwrap();
        let svg = "<?xml version=\"1.0\"?>\n<svg width=\"10\" height=\"10\"><rect/></svg>\n";
        std::fs::write(dir.path().join("loss.svg"), svg).unwrap();
        let md = "# T\n\n| a | b |\n|---|---|\n| 1 | 2 |\n\n![the loss](loss.svg)\n\n![a photo](p.png)\n";
        let html = page("T <1>", md, dir.path()).unwrap();
        assert!(
            html.contains("<table>") && html.contains("<td>2</td>"),
            "{html}"
        );
        assert!(html.contains("<figure><svg width=\"10\""), "{html}");
        assert!(html.contains("<figcaption>the loss</figcaption>"), "{html}");
        assert!(
            !html.contains("loss.svg") && !html.contains("<?xml"),
            "{html}"
        );
        assert!(html.contains("<img src=\"p.png\""), "{html}");
        assert!(html.contains("<title>T &lt;1&gt;</title>"), "{html}");
        let missing = page("T", "![x](gone.svg)", dir.path()).unwrap_err();
        assert!(missing.to_string().contains("gone.svg"), "{missing}");
    }
}
