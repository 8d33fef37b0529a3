"""`millsense opcua`: an OPC UA server that shows every machine seen on Zenoh (the `opcua` extra).

The modules, in the order a sample travels:

- `inbox.py`: the Zenoh side. Subscribes to `millsense/*/{estimate,alarm,status,process}` and the
  liveliness tokens `millsense/*/alive`; hands each payload over one bounded, coalescing inbox.
- `fields.py`: which payload field becomes which OPC UA variable (pure: no asyncua, no Zenoh).
- `machine_nodes.py`: one machine's part of the address space, its tool life (OPC 40501 names) and
  its alarm events (an AlarmConditionType subtype).
- `conditions.py`: the condition instance at each event's ConditionId, its state from the events it fires.
- `acknowledge.py`: Acknowledge and Confirm of a condition, for operators only, audited.
- `feed_held.py`: the held feed as one retained condition per machine, `FeedHeld` (pure: when it goes
  active and inactive, and what its event says).
- `nodesets.py`: the OPC Foundation's NodeSet2 files (DI ... MachineTool) imported at start (issue 42).
- `machine_tool.py`: with them, one machine as an OPC 40501 MachineToolType under Objects/Machines.
- `where_clause.py`: an event filter's where clause evaluated as Part 4 says (OfType with subtypes, whole
  browse paths), over asyncua 2.1.0's evaluator: a client that watches only active conditions gets them.
- `settings.py`: the `[opcua]` section of `--config` (config/opcua_section.py) and the machine's identification.
- `security.py`: the server certificate, the trust list of client certificates, who may open a session.
- `server.py`: the asyncua Server and the loop that drains the inbox into the address space.

Nothing here is imported by the live daemon: asyncua is imported only by `millsense opcua`.
See docs/opcua.md.
"""
