"""mkdocs hook: the site's home page is the README, read at build time.

The README's links into ``docs/`` (``docs/method.md``) become links within the site
(``method.md``), and its pointer to the site points at the site itself. One source, so the
home page cannot fall behind the README.
"""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File, Files


def home_page(readme: str) -> str:
    text = readme.replace("](docs/", "](")
    return text.replace("are in [docs/](index.md)\n(a mkdocs site:", "are on this site\n(mkdocs:")


def on_files(files: Files, config) -> Files:
    readme = Path(config["config_file_path"]).parent / "README.md"
    old = files.get_file_from_path("index.md")
    if old is not None:
        files.remove(old)
    files.append(File.generated(config, "index.md", content=home_page(readme.read_text())))
    return files
