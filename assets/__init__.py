"""The bundled procedural rigs, installed as package data ``dqskin.assets`` (made by
``tools/make_assets.py``; see README.md here)."""
