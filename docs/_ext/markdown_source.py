"""Markdown pages as Sphinx sources: markdown-it-py's syntax tree turned into docutils nodes.

The pages under ``docs/`` (and the ``results.md`` each benchmark writes) are CommonMark with pipe
tables, read on GitHub as they are. Sphinx reads reStructuredText; the usual bridge, myst-parser, is
not on the package index this project installs from offline, so this one maps markdown-it-py's tree
(the parser myst-parser itself is built on) onto docutils nodes for what the pages use: headings,
paragraphs, lists, code, tables, emphasis, links and images (an image alone in its paragraph is a
figure, its alt text the caption). Anything else stops the build with the
page and line named, rather than vanishing from the site. The sources stay plain CommonMark, so
myst-parser can replace this file unchanged where it is available.

Links: a relative link to another page becomes a link to that page's HTML; one to a file of the
repository (a scene, a script) a download of it; one to a benchmark's results folder the results
page the build writes for it (``generated_pages``); anything else is left as the path in code.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from docutils import nodes
from markdown_it import MarkdownIt
from markdown_it.tree import SyntaxTreeNode
from sphinx import addnodes
from sphinx.parsers import Parser
from sphinx.util.logging import getLogger

LOGGER = getLogger(__name__)
# A page the build copies from elsewhere (generated_pages) names its original on its first line, so
# that its relative links and images resolve from where they were written.
ORIGIN = re.compile(r"<!-- origin: (\S+) -->\n")


class MarkdownError(Exception):
    """A construct the bridge does not carry, at a page's line."""


class MarkdownParser(Parser):
    """CommonMark with pipe tables, parsed into the document Sphinx hands over."""

    supported = ("markdown",)

    def parse(self, inputstring: str, document: nodes.document) -> None:
        origin = ORIGIN.match(inputstring)
        source = Path(document["source"]).resolve()
        if origin:
            inputstring = inputstring[origin.end():]
            source = (source.parent / origin.group(1)).resolve()
        tree = SyntaxTreeNode(MarkdownIt("commonmark").enable("table").parse(inputstring))
        try:
            _Builder(document, document.settings.env, source).build(tree)
        except MarkdownError as error:
            LOGGER.warning("%s", error, location=document["source"])


class _Builder:
    def __init__(self, document: nodes.document, env, source: Path):
        self.document = document
        self.env = env
        self.source = source
        self.here = Path(document["source"]).resolve().parent
        self.srcdir = Path(env.srcdir).resolve()
        self.root = (self.srcdir / env.config.repository_root).resolve()

    def build(self, tree: SyntaxTreeNode) -> None:
        sections: list[tuple[int, nodes.Element]] = [(0, self.document)]
        for block in tree.children:
            if block.type == "heading":
                level = int(block.tag[1])
                while sections[-1][0] >= level:
                    sections.pop()
                title = self.inlines(block.children[0])
                section = nodes.section()
                section += nodes.title("", "", *title)
                section["names"].append(nodes.fully_normalize_name(section.astext()))
                parent = sections[-1][1]
                parent += section
                self.document.note_implicit_target(section, section)
                sections.append((level, section))
            else:
                parent = sections[-1][1]
                parent += self.block(block)

    def block(self, node: SyntaxTreeNode) -> nodes.Node:
        kind = node.type
        if kind == "paragraph":
            content = self.inlines(node.children[0])
            if len(content) == 1 and isinstance(content[0], nodes.image):
                # An image on its own is a figure: numbered on the site (numfig), its alt text the caption.
                return nodes.figure("", content[0], nodes.caption("", content[0]["alt"]))
            return nodes.paragraph("", "", *content)
        if kind in ("bullet_list", "ordered_list"):
            out = nodes.bullet_list(bullet="-") if kind == "bullet_list" else nodes.enumerated_list(enumtype="arabic")
            for item in node.children:
                out += nodes.list_item("", *[self.block(child) for child in item.children])
            return out
        if kind in ("fence", "code_block"):
            language = (node.info or "").strip().split(" ")[0] or "text"
            text = node.content.rstrip("\n")
            return nodes.literal_block(text, text, language=language)
        if kind == "blockquote":
            return nodes.block_quote("", *[self.block(child) for child in node.children])
        if kind == "table":
            return self.table(node)
        raise self.unsupported(kind, node)

    def table(self, node: SyntaxTreeNode) -> nodes.table:
        head, *body = node.children
        header = head.children[0]
        group = nodes.tgroup(cols=len(header.children))
        group += [nodes.colspec(colwidth=1) for _ in header.children]
        group += nodes.thead("", self.row(header))
        if body:
            group += nodes.tbody("", *[self.row(tr) for tr in body[0].children])
        return nodes.table("", group)

    def row(self, tr: SyntaxTreeNode) -> nodes.row:
        return nodes.row("", *[nodes.entry("", nodes.paragraph("", "", *self.inlines(cell.children[0])))
                               if cell.children else nodes.entry() for cell in tr.children])

    def inlines(self, inline: SyntaxTreeNode) -> list[nodes.Node]:
        out: list[nodes.Node] = []
        for node in inline.children:
            kind = node.type
            if kind == "text":
                out.append(nodes.Text(node.content))
            elif kind == "softbreak":
                out.append(nodes.Text(" "))
            elif kind == "hardbreak":
                out.append(nodes.raw("", "<br/>", format="html"))
            elif kind == "code_inline":
                out.append(nodes.literal(node.content, node.content))
            elif kind == "strong":
                out.append(nodes.strong("", "", *self.inlines(node)))
            elif kind == "em":
                out.append(nodes.emphasis("", "", *self.inlines(node)))
            elif kind == "link":
                out.append(self.link(node))
            elif kind == "image":
                out.append(self.image(node))
            else:
                raise self.unsupported(kind, inline)
        return out

    def link(self, node: SyntaxTreeNode) -> nodes.Node:
        href = str(node.attrs["href"])
        text = self.inlines(node)
        if href.startswith(("http://", "https://", "mailto:", "#")):  # another site, or a place on this page
            return nodes.reference("", "", *text, refuri=href)
        path, _, anchor = href.partition("#")
        target = (self.source.parent / path).resolve()
        page = self.page_of(target)
        if page is not None:
            uri = self.relative(self.srcdir / f"{page}.html") + (f"#{anchor}" if anchor else "")
            return nodes.reference("", "", *text, refuri=uri, internal=True)
        if target.is_file():
            return addnodes.download_reference("", "", nodes.literal("", "", *text), refdoc=self.env.docname,
                                               reftarget=self.relative(target), refexplicit=True)
        return nodes.inline("", "", *text, nodes.Text(" ("),
                            nodes.literal(href, target.relative_to(self.root).as_posix()
                                          if target.is_relative_to(self.root) else href), nodes.Text(")"))

    def image(self, node: SyntaxTreeNode) -> nodes.image:
        src = str(node.attrs["src"])
        if not src.startswith(("http://", "https://")):
            src = self.relative(self.source.parent / src)
        return nodes.image(uri=src, alt=node.content or "")

    def relative(self, path: Path) -> str:
        """``path`` from the page's own folder (pages and their HTML sit alike in the tree)."""
        return Path(os.path.relpath(path, self.here)).as_posix()

    def page_of(self, target: Path) -> str | None:
        """The docname a link's target is shown as, or None where it is no page of the site."""
        if target == self.root / "README.md":
            return "generated/start"
        results = self.root / "benchmarks" / "results"
        if target.is_relative_to(results) and target != results:
            return f"generated/results/{target.relative_to(results).parts[0]}"
        if target.suffix in (".md", ".rst") and target.is_relative_to(self.srcdir):
            docname = target.relative_to(self.srcdir).with_suffix("").as_posix()
            if docname in self.env.found_docs:
                return docname
        return None

    @staticmethod
    def unsupported(kind: str, node: SyntaxTreeNode) -> MarkdownError:
        line = (node.map[0] + 1) if node.map else 0
        return MarkdownError(f"line {line}: markdown {kind!r} has no counterpart here (docs/_ext/markdown_source.py)")


def setup(app):
    app.add_config_value("repository_root", "..", "env")
    app.add_source_suffix(".md", "markdown")
    app.add_source_parser(MarkdownParser)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
