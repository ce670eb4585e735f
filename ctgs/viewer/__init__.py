"""`ctgs view`: a WebGL2 viewer of textured Gaussian surfels (static page + local HTTP server).

server.py serves static/ (HTML, JS, GLSL; nothing from the internet) and a web bundle
(ctgs.formats.web_bundle); headless.py drives a headless Chromium for the tests and benchmarks.
"""
