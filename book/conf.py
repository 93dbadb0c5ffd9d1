"""Sphinx configuration of the flowmod book (Sphinx + myst-nb + sphinx-book-theme).

The book renders notebooks that papermill already executed (``nb_execution_mode = "off"``):
``python -m flowmod.report.book`` copies these sources and the executed notebooks into a staging
folder and runs ``sphinx-build -W -n --keep-going`` there. MathJax is served from the book
itself (vendored from npm ``mathjax@3`` by ``make env``), so the built book makes no network
request.
"""

import os

project = "flowmod: optical-flow motion detection, reproduced"
author = "the flowmod authors"
copyright = "2026, the flowmod authors"

extensions = ["myst_nb"]
nb_execution_mode = "off"
nb_merge_streams = True
# progress bars and library warnings stay in the executed notebooks, not in the book
nb_output_stderr = "remove"
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3
exclude_patterns = ["_build", "**.ipynb_checkpoints", "conf.py"]
suppress_warnings = ["mystnb.unknown_mime_type"]

html_theme = "sphinx_book_theme"
html_title = "flowmod"
html_static_path = ["_static"]
html_css_files = ["flowmod.css"]
html_theme_options = {
    "show_toc_level": 2,
    "use_download_button": False,
    "use_fullscreen_button": False,
    "use_repository_button": False,
    "navigation_with_keys": False,
}
html_last_updated_fmt = ""

# Offline MathJax: the staging step puts mathjax@3's es5/ folder in a static folder, so it is
# served from <html>/_static/_vendor/mathjax (a relative mathjax_path is relative to _static).
if os.environ.get("FLOWMOD_MATHJAX_EXTRA"):
    html_static_path.append(os.environ["FLOWMOD_MATHJAX_EXTRA"])
mathjax_path = "_vendor/mathjax/tex-chtml.js"

# Videos that notebooks show as raw HTML (media/<name>.mp4): copied to <html>/media.
if os.environ.get("FLOWMOD_PAGES_EXTRA"):
    html_extra_path = [os.environ["FLOWMOD_PAGES_EXTRA"]]
