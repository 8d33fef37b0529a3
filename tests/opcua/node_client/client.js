// A foreign OPC UA client (node-opcua, not asyncua) for tests/opcua/test_node_client.py (issue 42).
//
// Driven by the Python test: one JSON object of options as the only argument, one JSON line on stdout per
// step (`{"step": ..., ...}`), then exit 0; a failure is one `{"step": "error", ...}` line and exit 1.
// What it does is what a plant's alarms-and-conditions HMI and an umati-style dashboard do:
//   1. connects under each security policy it is given (certificate user, Sign & Encrypt) and reads the Server
//      object's name; tries once with a certificate the server does not trust;
//   2. subscribes to the Server object's events, says "subscribed" (the test starts the daemon then);
//   3. browses Objects/Machines for the object whose TypeDefinition is MachineToolType (ns MachineTool, i=13),
//      reads its Identification, and subscribes to millsense's torque_nm one reference away;
//   4. waits for the overload's condition event and the held feed's, calls ConditionRefresh and reports the
//      conditions it replays (to the item that takes every event, and to a second item of the same subscription
//      that watches only active conditions: where clause `OfType(AlarmConditionType) AND ActiveState/Id = true`); acknowledges the overload's condition (its last EventId, read from the
//      condition's node) and reads its AckedState, then confirms it and reads its ConfirmedState.
// Nothing in it is written for millsense's server only: standard services, standard NodeIds, browse names.
"use strict";

const fs = require("fs");
const path = require("path");
const {
    OPCUAClient, MessageSecurityMode, SecurityPolicy, UserTokenType, AttributeIds, TimestampsToReturn, DataType,
    ClientMonitoredItem, constructEventFilter, makeBrowsePath, resolveNodeId, BrowseDirection, NodeClassMask,
    callConditionRefresh, acknowledgeCondition, confirmCondition, makeContentFilter, and, ofType, s: operand, l: literal,
    ContentFilterElement, FilterOperator
} = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
const { readCertificate, readPrivateKey, keyOperationsFromPrivateKey } = require("node-opcua-crypto");

const opts = JSON.parse(process.argv[2]);
const MT_NS = "http://opcfoundation.org/UA/MachineTool/";
const DI_NS = "http://opcfoundation.org/UA/DI/";
const MACHINERY_NS = "http://opcfoundation.org/UA/Machinery/";
const MS_NS = "urn:millsense:opcua";
const MACHINE_TOOL_TYPE = 13; // OPC 40501 NodeIds.csv
const EVENT_FIELDS = ["EventId", "EventType", "ConditionName", "ActiveState.Id", "AckedState.Id", "Retain",
    "Severity", "Message", "SourceName", "Time", "ConditionId"];
const REFRESH_START = "ns=0;i=2787"; // RefreshStartEventType (a NodeId as node-opcua writes it)
const REFRESH_END = "ns=0;i=2788";   // RefreshEndEventType
// What an alarm list of the active conditions only puts on the wire (Part 4 7.7): AlarmConditionType or a subtype,
// and its ActiveState/Id true.
const ACTIVE_ONLY = makeContentFilter(and(ofType("i=2915"), new ContentFilterElement({
    filterOperator: FilterOperator.Equals,
    filterOperands: [operand(AttributeIds.Value, "ActiveState.Id"), literal(DataType.Boolean, true)],
})));

function say(step, fields) {
    process.stdout.write(JSON.stringify({ step, ...fields }) + "\n");
}

function sleep(ms) {
    return new Promise((resolve) => setTimeout(resolve, ms));
}

async function until(what, probe) {
    const deadline = Date.now() + opts.timeout_s * 1000;
    for (;;) {
        const value = await probe();
        if (value) return value;
        if (Date.now() > deadline) throw new Error(`timed out after ${opts.timeout_s} s: ${what}`);
        await sleep(50);
    }
}

// One certificate manager in the test's folder (never the user's home), trusting the server's certificate only.
async function certificateManager() {
    const root = path.join(opts.pki_dir, "node-opcua");
    const manager = new OPCUACertificateManager({ rootFolder: root, automaticallyAcceptUnknownCertificate: false });
    await manager.initialize();
    fs.copyFileSync(opts.server_cert, path.join(root, "trusted", "certs", "server.der"));
    return manager;
}

async function session(manager, policy, cert, key) {
    const client = OPCUAClient.create({
        applicationName: "node-opcua test client",
        applicationUri: opts.application_uri,
        securityMode: MessageSecurityMode.SignAndEncrypt,
        securityPolicy: SecurityPolicy[policy],
        certificateFile: cert,
        privateKeyFile: key,
        clientCertificateManager: manager,
        endpointMustExist: true,
        connectionStrategy: { maxRetry: 0 },
        requestedSessionTimeout: 60000,
    });
    await client.connect(opts.endpoint);
    try {
        const s = await client.createSession({
            type: UserTokenType.Certificate, certificateData: readCertificate(cert),
            keyOperations: keyOperationsFromPrivateKey(readPrivateKey(key)),
        });
        return { client, session: s };
    } catch (err) {
        await client.disconnect();
        throw err;
    }
}

async function close(pair) {
    await pair.session.close();
    await pair.client.disconnect();
}

async function translate(s, start, relative) {
    const result = await s.translateBrowsePath(makeBrowsePath(start, relative));
    if (!result.statusCode.isGood() || !result.targets.length) {
        throw new Error(`browse path ${start}${relative}: ${result.statusCode.toString()}`);
    }
    return result.targets[0].targetId;
}

async function readValue(s, nodeId) {
    const dv = await s.read({ nodeId, attributeId: AttributeIds.Value });
    return dv;
}

async function supertypes(s, nodeId) {
    const chain = [];
    const typeRef = await s.browse({ nodeId, browseDirection: BrowseDirection.Forward, includeSubtypes: false,
        referenceTypeId: resolveNodeId("HasTypeDefinition"), resultMask: 63 });
    let type = typeRef.references[0].nodeId;
    while (type) {
        chain.push(type.toString());
        const up = await s.browse({ nodeId: type, browseDirection: BrowseDirection.Inverse, includeSubtypes: false,
            referenceTypeId: resolveNodeId("HasSubtype"), resultMask: 63 });
        type = up.references && up.references.length ? up.references[0].nodeId : null;
    }
    return chain;
}

function text(value) {
    return value && typeof value === "object" && "text" in value ? value.text : value;
}

function eventOf(fields) {
    const e = {};
    EVENT_FIELDS.forEach((name, i) => {
        const v = fields[i];
        e[name] = v && v.dataType !== DataType.Null ? v.value : null;
    });
    return {
        event_id: e.EventId ? e.EventId.toString("hex") : null,
        event_type: e.EventType ? e.EventType.toString() : null,
        condition: e.ConditionName, active: e["ActiveState.Id"], acked: e["AckedState.Id"], retain: e.Retain,
        severity: e.Severity, message: text(e.Message), source: e.SourceName,
        condition_id: e.ConditionId ? e.ConditionId.toString() : null,
    };
}

async function policies(manager) {
    for (const policy of opts.policies) {
        try {
            const pair = await session(manager, policy, opts.client_cert, opts.client_key);
            const name = await pair.session.read({ nodeId: "i=2253", attributeId: AttributeIds.BrowseName });
            say("policy", { policy, ok: true, server: name.value.value.name });
            await close(pair);
        } catch (err) {
            say("policy", { policy, ok: false, error: String(err.message || err).split("\n")[0] });
        }
    }
    try {
        const pair = await session(manager, opts.policies[0], opts.stranger_cert, opts.stranger_key);
        say("stranger", { ok: true });
        await close(pair);
    } catch (err) {
        say("stranger", { ok: false, error: String(err.message || err).split("\n")[0] });
    }
}

async function main() {
    const manager = await certificateManager();
    await policies(manager);
    const pair = await session(manager, opts.main_policy, opts.client_cert, opts.client_key);
    const s = pair.session;
    try {
        const namespaces = (await readValue(s, "i=2255")).value.value;
        const ns = (uri) => {
            const i = namespaces.indexOf(uri);
            if (i < 0) throw new Error(`namespace ${uri} not in the server's NamespaceArray`);
            return i;
        };
        const mt = ns(MT_NS), di = ns(DI_NS), machinery = ns(MACHINERY_NS), ms = ns(MS_NS);

        const events = [];
        const subscription = await s.createSubscription2({
            requestedPublishingInterval: 50, requestedLifetimeCount: 600, requestedMaxKeepAliveCount: 20,
            maxNotificationsPerPublish: 0, publishingEnabled: true, priority: 1,
        });
        // An event item on the Server object: each event to `onEvent`, except ConditionRefresh's replay, which
        // the item keeps from RefreshStart to RefreshEnd and then hands over as `refreshed` (null until then).
        const watch = (filter, onEvent) => {
            const item = ClientMonitoredItem.create(subscription,
                { nodeId: resolveNodeId("Server"), attributeId: AttributeIds.EventNotifier },
                { samplingInterval: 0, queueSize: 1000, discardOldest: false, filter },
                TimestampsToReturn.Both);
            const watched = { item, refreshed: null };
            let refreshing = null;
            item.on("changed", (fields) => {
                const e = eventOf(fields);
                if (e.event_type === REFRESH_START) { refreshing = []; return; }
                if (e.event_type === REFRESH_END) { watched.refreshed = refreshing; refreshing = null; return; }
                if (refreshing !== null) { refreshing.push(e); return; }
                onEvent(e);
            });
            return watched;
        };
        const all = watch(constructEventFilter(EVENT_FIELDS), (e) => { events.push(e); say("event", e); });
        // The client that watches only active conditions: its own item, its own refresh window.
        const active = watch(constructEventFilter(EVENT_FIELDS, ACTIVE_ONLY), (e) => say("active_event", e));
        await until("the event subscription", async () =>
            all.item.monitoredItemId !== undefined && active.item.monitoredItemId !== undefined);
        say("subscribed", { subscription_id: subscription.subscriptionId });

        // 3. The machine by its type: browse Objects/Machines, check each child's TypeDefinition.
        const machines = await translate(s, resolveNodeId("ObjectsFolder"), `/${machinery}:Machines`);
        const machine = await until("a MachineToolType object under Objects/Machines", async () => {
            const found = await s.browse({ nodeId: machines, browseDirection: BrowseDirection.Forward,
                includeSubtypes: true, nodeClassMask: NodeClassMask.Object, resultMask: 63,
                referenceTypeId: resolveNodeId("HierarchicalReferences") });
            for (const ref of found.references || []) {
                const td = ref.typeDefinition;
                if (td.namespace === mt && td.value === MACHINE_TOOL_TYPE) return ref;
            }
            return null;
        });
        say("machine", { browse_name: machine.browseName.name, type_definition: machine.typeDefinition.toString(),
            type_namespace: namespaces[machine.typeDefinition.namespace] });
        const machineId = machine.nodeId;
        const identification = {};
        for (const field of ["Manufacturer", "SerialNumber", "ProductInstanceUri"]) {
            const id = await translate(s, machineId, `/${di}:Identification/${di}:${field}`);
            identification[field] = text((await readValue(s, id)).value.value);
        }
        say("identification", identification);

        // millsense's torque, one reference from the instance; each value with its source timestamp.
        const torqueId = await translate(s, machineId, `/${ms}:${opts.machine}/${ms}:Spindle/${ms}:torque_nm`);
        const torque = [];
        const torqueItem = ClientMonitoredItem.create(subscription,
            { nodeId: torqueId, attributeId: AttributeIds.Value },
            { samplingInterval: 0, queueSize: 100, discardOldest: true }, TimestampsToReturn.Both);
        torqueItem.on("changed", (dv) => {
            if (!dv.statusCode.isGood() || !dv.sourceTimestamp) return;
            const t = dv.sourceTimestamp.getTime() / 1000 + (dv.sourcePicoseconds || 0) / 1e12;
            torque.push(t);
            if (torque.length <= opts.torque_values) say("torque", { value: dv.value.value, source_t: t });
        });
        await until(`${opts.torque_values} torque values`, async () => torque.length >= opts.torque_values);

        // 4. The overload as a condition, the held feed, ConditionRefresh, Acknowledge.
        const overload = await until("the overload's condition event", async () =>
            events.find((e) => e.condition === opts.overload_condition && e.active === true));
        await until("the held feed's condition event", async () =>
            events.find((e) => e.condition === "FeedHeld" && e.active === true));
        // Refresh only once the overload's own condition has cleared: what a client connecting to a stopped,
        // held machine would get.
        await until("the overload's condition cleared", async () =>
            events.find((e) => e.condition === opts.overload_condition && e.active === false));
        const refreshStatus = await callConditionRefresh(s, subscription.subscriptionId);
        say("refresh_called", { status: refreshStatus.name });
        const replayed = await until("ConditionRefresh's RefreshEnd", async () => all.refreshed);
        say("refreshed", { conditions: replayed });
        // The same refresh, as the item that watches only active conditions got it (RefreshStart and RefreshEnd
        // ignore its filter: Part 9 5.5.7).
        say("active_refreshed", { conditions: await until("the active-only item's RefreshEnd", async () =>
            active.refreshed) });

        // Each condition's type, by its TypeDefinition and the supertypes up to Part 9's (standard, ns 0) ones; the
        // overload's HighLimit.
        const types = {};
        for (const e of [overload, events.find((x) => x.condition === "FeedHeld")]) {
            types[e.condition] = await supertypes(s, resolveNodeId(e.condition_id));
        }
        const highLimit = await translate(s, resolveNodeId(overload.condition_id), ".HighLimit");
        say("types", { types, high_limit: (await readValue(s, highLimit)).value.value });

        // Acknowledge the overload's condition: its last EventId, as the condition's node says it now.
        const conditionId = resolveNodeId(overload.condition_id);
        const eventIdNode = await translate(s, conditionId, ".EventId");
        let status = null;
        for (let attempt = 0; attempt < 3; attempt++) {
            const eventId = (await readValue(s, eventIdNode)).value.value;
            status = await acknowledgeCondition(s, conditionId, eventId, opts.comment);
            if (status.name !== "BadEventIdUnknown") break; // a newer event came between the read and the call
        }
        say("acknowledged", { status: status.name, condition_id: overload.condition_id });
        const ackedId = await translate(s, conditionId, ".AckedState.Id");
        say("acked_state", { acked: (await readValue(s, ackedId)).value.value });
        await until("the acknowledgement's event", async () =>
            events.find((e) => e.condition === opts.overload_condition && e.acked === true));
        // Confirm it: the EventId of the acknowledgement's event, as the condition's node says it now.
        for (let attempt = 0; attempt < 3; attempt++) {
            const eventId = (await readValue(s, eventIdNode)).value.value;
            status = await confirmCondition(s, conditionId, eventId, opts.comment);
            if (status.name !== "BadEventIdUnknown") break;
        }
        const confirmedId = await translate(s, conditionId, ".ConfirmedState.Id");
        say("confirmed", { status: status.name, confirmed: (await readValue(s, confirmedId)).value.value });
        await subscription.terminate();
    } finally {
        await close(pair);
    }
    const cpu = process.cpuUsage();
    say("done", { cpu_s: (cpu.user + cpu.system) / 1e6 }); // its own CPU time, for whoever watches the suite's cost
}

main().then(() => process.exit(0), (err) => {
    say("error", { error: String((err && err.stack) || err) });
    process.exit(1);
});
