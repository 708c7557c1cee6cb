"""The display side without ROS: the scene a client sees (scene.py: meshes per agent and garment, their frames and
the nodes' status), the HTTPS + WebSocket server of the three.js client in web/ (server.py) and its self-signed
certificate (tls.py), and what the node publishes for display (models.py: no skin through the cloth, garments
layered, a smooth mesh). Import the modules themselves: the server needs `websockets`, the node never does."""
