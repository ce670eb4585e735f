"""The ground floor's file helpers: atomic writes and replacements (atomic), signals held while a block runs
(signals), versioned JSON files read back (versioned), images (images), downloads (download). File formats and
codecs live in ctgs.formats."""
