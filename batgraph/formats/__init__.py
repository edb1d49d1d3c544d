"""Readers and writers of other tools' file formats (DLTdv, Argus); session folders: batgraph.session."""
