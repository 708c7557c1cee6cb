"""The web viewer without ROS: the scene a client sees (state.py: meshes per agent and garment, their frames and the
nodes' status), the HTTPS + WebSocket server of the three.js client in web/ (server.py) and its self-signed
certificate (tls.py). ros/viewer.py feeds it from the topics. Import the modules themselves: the server needs
`websockets`, the node never does."""
