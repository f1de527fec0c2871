//! A small hand-written SVG plotter: axes with round-number ticks, points,
//! lines, bars and text. Enough for the report's handful of plots, without a
//! plotting crate and its font stack (the browser draws the text).

use std::fmt::Write as _;

/// Escapes text for SVG/HTML content and attributes.
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            _ => out.push(c),
        }
    }
    out
}

/// Colours of series, by robot order (colour-blind-safe Okabe-Ito).
pub const PALETTE: [&str; 6] = [
    "#0072B2", "#E69F00", "#009E73", "#CC79A7", "#56B4E9", "#D55E00",
];
pub const GREY: &str = "#888888";
pub const RED: &str = "#C0392B";
pub const GREEN: &str = "#2E8B57";

/// An SVG document under construction.
#[derive(Debug)]
pub struct Svg {
    width: f64,
    height: f64,
    body: String,
}

impl Svg {
    pub fn new(width: f64, height: f64) -> Self {
        Svg {
            width,
            height,
            body: String::new(),
        }
    }

    pub fn finish(self) -> String {
        format!(
            "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" \
             viewBox=\"0 0 {w} {h}\" font-family=\"DejaVu Sans, Arial, sans-serif\" font-size=\"12\">\n\
             <rect width=\"{w}\" height=\"{h}\" fill=\"white\"/>\n{}</svg>\n",
            self.body,
            w = self.width,
            h = self.height
        )
    }

    pub fn raw(&mut self, s: &str) {
        self.body.push_str(s);
        self.body.push('\n');
    }

    pub fn line(&mut self, x1: f64, y1: f64, x2: f64, y2: f64, stroke: &str, width: f64) {
        let _ = writeln!(
            self.body,
            "<line x1=\"{x1:.2}\" y1=\"{y1:.2}\" x2=\"{x2:.2}\" y2=\"{y2:.2}\" stroke=\"{stroke}\" stroke-width=\"{width}\"/>"
        );
    }

    pub fn dashed(&mut self, x1: f64, y1: f64, x2: f64, y2: f64, stroke: &str, width: f64) {
        let _ = writeln!(
            self.body,
            "<line x1=\"{x1:.2}\" y1=\"{y1:.2}\" x2=\"{x2:.2}\" y2=\"{y2:.2}\" stroke=\"{stroke}\" stroke-width=\"{width}\" stroke-dasharray=\"6 4\"/>"
        );
    }

    pub fn rect(&mut self, x: f64, y: f64, w: f64, h: f64, fill: &str, title: Option<&str>) {
        match title {
            Some(t) => {
                let _ = writeln!(
                    self.body,
                    "<rect x=\"{x:.2}\" y=\"{y:.2}\" width=\"{:.2}\" height=\"{:.2}\" fill=\"{fill}\"><title>{}</title></rect>",
                    w.max(0.0),
                    h.max(0.0),
                    escape(t)
                );
            }
            None => {
                let _ = writeln!(
                    self.body,
                    "<rect x=\"{x:.2}\" y=\"{y:.2}\" width=\"{:.2}\" height=\"{:.2}\" fill=\"{fill}\"/>",
                    w.max(0.0),
                    h.max(0.0)
                );
            }
        }
    }

    pub fn circle(&mut self, x: f64, y: f64, r: f64, fill: &str, title: Option<&str>) {
        let t = title.map_or(String::new(), |t| format!("<title>{}</title>", escape(t)));
        let _ = writeln!(
            self.body,
            "<circle cx=\"{x:.2}\" cy=\"{y:.2}\" r=\"{r}\" fill=\"{fill}\" fill-opacity=\"0.85\" stroke=\"white\" stroke-width=\"0.8\">{t}</circle>"
        );
    }

    pub fn ring(&mut self, x: f64, y: f64, r: f64, stroke: &str) {
        let _ = writeln!(
            self.body,
            "<circle cx=\"{x:.2}\" cy=\"{y:.2}\" r=\"{r:.2}\" fill=\"none\" stroke=\"{stroke}\" stroke-width=\"1\"/>"
        );
    }

    pub fn cross(&mut self, x: f64, y: f64, r: f64, stroke: &str, title: Option<&str>) {
        let t = title.map_or(String::new(), |t| format!("<title>{}</title>", escape(t)));
        let _ = writeln!(
            self.body,
            "<path d=\"M{:.2} {:.2}L{:.2} {:.2}M{:.2} {:.2}L{:.2} {:.2}\" stroke=\"{stroke}\" stroke-width=\"2\">{t}</path>",
            x - r,
            y - r,
            x + r,
            y + r,
            x - r,
            y + r,
            x + r,
            y - r
        );
    }

    pub fn polyline(&mut self, points: &[(f64, f64)], stroke: &str, width: f64) {
        if points.len() < 2 {
            return;
        }
        let pts: Vec<String> = points
            .iter()
            .map(|(x, y)| format!("{x:.2},{y:.2}"))
            .collect();
        let _ = writeln!(
            self.body,
            "<polyline points=\"{}\" fill=\"none\" stroke=\"{stroke}\" stroke-width=\"{width}\" stroke-opacity=\"0.6\"/>",
            pts.join(" ")
        );
    }

    /// Text; `anchor` is `start`, `middle` or `end`.
    pub fn text(&mut self, x: f64, y: f64, s: &str, anchor: &str, size: f64, fill: &str) {
        let _ = writeln!(
            self.body,
            "<text x=\"{x:.2}\" y=\"{y:.2}\" text-anchor=\"{anchor}\" font-size=\"{size}\" fill=\"{fill}\">{}</text>",
            escape(s)
        );
    }

    /// Text rotated 90 degrees counter-clockwise (a y-axis label).
    pub fn vtext(&mut self, x: f64, y: f64, s: &str, size: f64) {
        let _ = writeln!(
            self.body,
            "<text x=\"{x:.2}\" y=\"{y:.2}\" text-anchor=\"middle\" font-size=\"{size}\" transform=\"rotate(-90 {x:.2} {y:.2})\">{}</text>",
            escape(s)
        );
    }
}

/// Round-number ticks covering `[lo, hi]`: about `n` of them, step 1, 2 or 5
/// times a power of ten. Returns (ticks, step).
pub fn nice_ticks(lo: f64, hi: f64, n: usize) -> (Vec<f64>, f64) {
    let (lo, hi) = if hi > lo {
        (lo, hi)
    } else {
        (lo - 0.5, lo + 0.5)
    };
    let raw = (hi - lo) / n.max(1) as f64;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag);
    let first = (lo / step).floor() * step;
    let mut ticks = Vec::new();
    let mut t = first;
    while t <= hi + step * 1e-9 {
        ticks.push(if t.abs() < step * 1e-9 { 0.0 } else { t });
        t += step;
        if ticks.len() > 100 {
            break;
        }
    }
    if ticks.last().is_some_and(|l| *l < hi) {
        ticks.push(t);
    }
    (ticks, step)
}

/// Formats a tick value with just enough decimals for its step.
pub fn fmt_tick(v: f64, step: f64) -> String {
    let decimals = if step >= 1.0 {
        0
    } else {
        (-step.log10()).ceil().max(0.0) as usize
    };
    format!("{v:.decimals$}")
}

/// A rectangular data area with linear axes.
#[derive(Debug, Clone)]
pub struct Axes {
    pub left: f64,
    pub top: f64,
    pub width: f64,
    pub height: f64,
    pub x0: f64,
    pub x1: f64,
    pub y0: f64,
    pub y1: f64,
    pub xstep: f64,
    pub ystep: f64,
    xticks: Vec<f64>,
    yticks: Vec<f64>,
}

impl Axes {
    /// Axes in a `w` x `h` SVG, covering the data ranges (expanded to round ticks).
    pub fn new(w: f64, h: f64, (xlo, xhi): (f64, f64), (ylo, yhi): (f64, f64)) -> Self {
        let (xticks, xstep) = nice_ticks(xlo, xhi, 8);
        let (yticks, ystep) = nice_ticks(ylo, yhi, 5);
        let (left, top, right, bottom) = (62.0, 50.0, 16.0, 46.0);
        Axes {
            left,
            top,
            width: w - left - right,
            height: h - top - bottom,
            x0: xticks[0],
            x1: *xticks.last().unwrap_or(&xhi),
            y0: yticks[0],
            y1: *yticks.last().unwrap_or(&yhi),
            xstep,
            ystep,
            xticks,
            yticks,
        }
    }

    pub fn x(&self, v: f64) -> f64 {
        self.left + (v - self.x0) / (self.x1 - self.x0) * self.width
    }

    pub fn y(&self, v: f64) -> f64 {
        self.top + self.height - (v - self.y0) / (self.y1 - self.y0) * self.height
    }

    /// Frame, grid, ticks, axis labels and title.
    pub fn draw(&self, svg: &mut Svg, title: &str, xlabel: &str, ylabel: &str, integer_x: bool) {
        for &t in &self.yticks {
            let y = self.y(t);
            svg.line(self.left, y, self.left + self.width, y, "#e4e4e4", 1.0);
            svg.text(
                self.left - 6.0,
                y + 4.0,
                &fmt_tick(t, self.ystep),
                "end",
                11.0,
                "#333",
            );
        }
        for &t in &self.xticks {
            if integer_x && t.fract() != 0.0 {
                continue;
            }
            let x = self.x(t);
            svg.line(
                x,
                self.top + self.height,
                x,
                self.top + self.height + 4.0,
                "#333",
                1.0,
            );
            svg.text(
                x,
                self.top + self.height + 17.0,
                &fmt_tick(t, self.xstep.max(if integer_x { 1.0 } else { 0.0 })),
                "middle",
                11.0,
                "#333",
            );
        }
        svg.raw(&format!(
            "<rect x=\"{:.2}\" y=\"{:.2}\" width=\"{:.2}\" height=\"{:.2}\" fill=\"none\" stroke=\"#333\" stroke-width=\"1\"/>",
            self.left, self.top, self.width, self.height
        ));
        svg.text(self.left, 18.0, title, "start", 14.0, "#111");
        svg.text(
            self.left + self.width / 2.0,
            self.top + self.height + 38.0,
            xlabel,
            "middle",
            12.0,
            "#111",
        );
        svg.vtext(16.0, self.top + self.height / 2.0, ylabel, 12.0);
    }
}

/// The baseline of a legend row, under the title.
pub const LEGEND_Y: f64 = 38.0;

/// A legend row at the top right: (colour, label) pairs.
pub fn legend(svg: &mut Svg, right: f64, y: f64, entries: &[(String, String)]) {
    let mut x = right;
    for (colour, label) in entries.iter().rev() {
        let w = 7.0 * label.chars().count() as f64 + 22.0;
        x -= w;
        svg.rect(x, y - 9.0, 12.0, 12.0, colour, None);
        svg.text(x + 16.0, y + 1.0, label, "start", 12.0, "#111");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round_and_cover_the_range() {
        let (t, step) = nice_ticks(0.13, 0.87, 5);
        assert_eq!(step, 0.2);
        assert!(t[0] <= 0.13 && *t.last().unwrap() >= 0.87, "{t:?}");
        let (t, step) = nice_ticks(0.0, 37.0, 8);
        assert_eq!(step, 5.0);
        assert_eq!(t.first(), Some(&0.0));
        assert_eq!(t.last(), Some(&40.0));
        // A degenerate range still gives a usable axis.
        let (t, _) = nice_ticks(2.0, 2.0, 5);
        assert!(
            t.len() >= 2 && t[0] < 2.0 && *t.last().unwrap() > 2.0,
            "{t:?}"
        );
        assert_eq!(fmt_tick(0.30000000000000004, 0.1), "0.3");
        assert_eq!(fmt_tick(20.0, 5.0), "20");
    }

    #[test]
    fn text_is_escaped() {
        let mut s = Svg::new(10.0, 10.0);
        s.text(0.0, 0.0, "a<b & \"c\"", "start", 10.0, "#000");
        let out = s.finish();
        assert!(out.contains("a&lt;b &amp; &quot;c&quot;"), "{out}");
    }
}
