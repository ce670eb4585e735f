"""The ground floor's file helpers: atomic writes and replacements (atomic), images (images), downloads
(download). File formats and codecs live in ctgs.formats."""
