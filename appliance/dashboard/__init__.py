"""The dashboard: the thesis GUIs as one live web app (issue 22)."""
