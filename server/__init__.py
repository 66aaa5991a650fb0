"""The web application: FastAPI app (``server.main.create_app``), session manager with SLAM
worker processes (``server.sessions``), live viser viewer (``server.viewer``), and the
``voxfusion serve`` / ``voxfusion demo`` commands (``server.cli``). See server/README.md."""
