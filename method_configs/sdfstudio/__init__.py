"""sdfstudio (commit 370902a) method configs, one module per method; read by sp_plugins.sdfstudio.registration."""
