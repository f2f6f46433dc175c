// MathJax 3 for the site: arithmatex spans on Markdown pages (\( \), \[ \]) and the
// notebooks' Markdown cells ($ $, $$ $$); nothing else on a page is typeset.
// MathJax itself is javascripts/mathjax/tex-chtml-full.js, served from the site (no
// network needed); it loads its fonts from javascripts/mathjax/output/chtml/fonts/.
window.MathJax = {
  tex: {
    inlineMath: [["\\(", "\\)"], ["$", "$"]],
    displayMath: [["\\[", "\\]"], ["$$", "$$"]],
    processEscapes: true,
    processEnvironments: true
  },
  options: {
    // Every element with a class is skipped, and so is all that it contains, except
    // inside the two classes below. Elements without a class inherit from their parent,
    // so the <p> of a notebook's Markdown cell is typeset. (The pattern ".*|" also
    // matched an empty class, which skipped those paragraphs: the notebooks' formulas
    // stayed raw TeX.)
    ignoreHtmlClass: ".+",
    processHtmlClass: "arithmatex|jp-RenderedMarkdown"
  }
};

// MathJax typesets the first page itself when it starts. Material's document$ emits
// again only on an instant page change (navigation.instant, not enabled here), where the
// new page is typeset afresh. The output's character cache is not cleared:
// MathJax.startup.output.clearCache() after the first typeset drops CommonHTML's glyph
// styles, and every formula then renders blank.
let firstPage = true
document$.subscribe(() => {
  if (firstPage || !window.MathJax.typesetPromise) {
    firstPage = false
    return
  }
  MathJax.typesetClear()
  MathJax.texReset()
  MathJax.typesetPromise()
})
