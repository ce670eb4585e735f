"""`ctgs view`: a WebGL2 viewer of textured Gaussian surfels (static page + local HTTP server).

server.py serves static/ (HTML, JS, GLSL; nothing from the internet) and a web bundle
(ctgs.formats.web_bundle). The tests and benchmarks drive the page in headless Chromium with benchmarks/headless.py
and benchmarks/viewer_page.py.
"""
