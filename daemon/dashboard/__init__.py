"""`millsense dashboard`: a web page of every machine seen on Zenoh (issue 16).

Three parts, one job each: `book.py` keeps what was seen (bounded per
machine) and fans updates out to the open pages; `zenoh_side.py` discovers
machines by their liveliness tokens, subscribes to their publications and
relays the reset exchange; `server.py` serves the page from `static/` and
the live updates as Server-Sent Events. Only the standard library and
eclipse-zenoh: a plant's network is closed, so nothing comes from a CDN.
"""
