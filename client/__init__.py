"""The client side of ``voxfusion stream``: it sends a camera, or a recording replayed in time,
to a running server over the server's WebSocket protocol (``server/routes_stream.py``).

``client.stream`` is the client (session, socket, back-pressure, progress, exit codes);
``client.open.open_source`` turns a source name into a frame source: a dataset folder or a
synthetic spec (``client.camera_sources.FolderSource``), a RealSense camera or recording
(``client.camera_sources.RealSenseSource``), a Record3D phone or ``.r3d`` file
(``client.record3d``). Nothing here imports FastAPI or the server; the ``voxfusion`` command
(``server.cli``) imports it only for its ``stream`` subcommand.
"""
