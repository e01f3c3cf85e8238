"""The dashboard: the thesis GUIs as one live web app (docs/dashboard.md)."""
