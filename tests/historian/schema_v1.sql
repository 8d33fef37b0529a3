-- tests/historian/test_schema.py: a database of the historian's schema version 1 (one day partition, one inferred
-- limit_changes row), as pg_dump --no-owner --no-privileges wrote it, for the upgrade to version 2. Made once, not edited.
--
-- PostgreSQL database dump
--

\restrict G1ZSU1opilveOArlFNvOgC44gEsIVjT15CSupF5kE5KOcvWvE1Pfks1pk0Cx3C1

-- Dumped from database version 15.18 (Debian 15.18-0+deb12u1)
-- Dumped by pg_dump version 15.18 (Debian 15.18-0+deb12u1)

SET statement_timeout = 0;
SET lock_timeout = 0;
SET idle_in_transaction_session_timeout = 0;
SET client_encoding = 'UTF8';
SET standard_conforming_strings = on;
SELECT pg_catalog.set_config('search_path', '', false);
SET check_function_bodies = false;
SET xmloption = content;
SET client_min_messages = warning;
SET row_security = off;

SET default_tablespace = '';

--
-- Name: alarms; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.alarms (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    level text NOT NULL,
    quantity text,
    value double precision,
    limit_value double precision,
    interlock text,
    rev bigint,
    run_id text,
    alarm_seq bigint,
    program bigint,
    tool bigint,
    operation integer,
    process bigint,
    process_rev bigint,
    expected double precision,
    reason text,
    payload jsonb NOT NULL
)
PARTITION BY RANGE ("time");


SET default_table_access_method = heap;

--
-- Name: alarms_default; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.alarms_default (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    level text NOT NULL,
    quantity text,
    value double precision,
    limit_value double precision,
    interlock text,
    rev bigint,
    run_id text,
    alarm_seq bigint,
    program bigint,
    tool bigint,
    operation integer,
    process bigint,
    process_rev bigint,
    expected double precision,
    reason text,
    payload jsonb NOT NULL
);


--
-- Name: limit_changes; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.limit_changes (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    key text NOT NULL,
    change text NOT NULL,
    envelope text,
    learned integer,
    process bigint
)
PARTITION BY RANGE ("time");


--
-- Name: limit_changes_default; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.limit_changes_default (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    key text NOT NULL,
    change text NOT NULL,
    envelope text,
    learned integer,
    process bigint
);


--
-- Name: limit_changes_p20261120; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.limit_changes_p20261120 (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    key text NOT NULL,
    change text NOT NULL,
    envelope text,
    learned integer,
    process bigint
);


--
-- Name: load_1s; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.load_1s (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    revolutions integer NOT NULL,
    valid integer NOT NULL,
    invalid integer NOT NULL,
    torque_min_nm double precision,
    torque_mean_nm double precision,
    torque_max_nm double precision,
    force_min_n double precision,
    force_mean_n double precision,
    force_max_n double precision,
    power_min_w double precision,
    power_mean_w double precision,
    power_max_w double precision
)
PARTITION BY RANGE ("time");


--
-- Name: load_1s_default; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.load_1s_default (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    revolutions integer NOT NULL,
    valid integer NOT NULL,
    invalid integer NOT NULL,
    torque_min_nm double precision,
    torque_mean_nm double precision,
    torque_max_nm double precision,
    force_min_n double precision,
    force_mean_n double precision,
    force_max_n double precision,
    power_min_w double precision,
    power_mean_w double precision,
    power_max_w double precision
);


--
-- Name: processes; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.processes (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    process bigint,
    key text,
    program bigint,
    tool bigint,
    operation integer,
    revolutions bigint,
    cutting_revolutions bigint,
    entry_rev bigint,
    torque_peak_nm double precision,
    torque_mean_nm double precision,
    force_peak_n double precision,
    energy_j double precision,
    verdict text,
    learned integer,
    learn_target integer,
    envelope text,
    energy_ratio double precision,
    tool_processes bigint,
    tool_wear_pct double precision,
    expected_band text,
    payload jsonb NOT NULL
)
PARTITION BY RANGE ("time");


--
-- Name: processes_default; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.processes_default (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    process bigint,
    key text,
    program bigint,
    tool bigint,
    operation integer,
    revolutions bigint,
    cutting_revolutions bigint,
    entry_rev bigint,
    torque_peak_nm double precision,
    torque_mean_nm double precision,
    force_peak_n double precision,
    energy_j double precision,
    verdict text,
    learned integer,
    learn_target integer,
    envelope text,
    energy_ratio double precision,
    tool_processes bigint,
    tool_wear_pct double precision,
    expected_band text,
    payload jsonb NOT NULL
);


--
-- Name: revolutions; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.revolutions (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    rev bigint NOT NULL,
    valid boolean NOT NULL,
    invalid text,
    spindle_rpm double precision,
    p_in_w double precision,
    p_gap_w double precision,
    torque_nm double precision,
    force_n double precision,
    radial_depth_mm double precision,
    axial_depth_mm double precision,
    depth_status text,
    feed_override_pct double precision,
    program bigint,
    tool bigint,
    operation integer,
    process_rev bigint
)
PARTITION BY RANGE ("time");


--
-- Name: revolutions_default; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.revolutions_default (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    rev bigint NOT NULL,
    valid boolean NOT NULL,
    invalid text,
    spindle_rpm double precision,
    p_in_w double precision,
    p_gap_w double precision,
    torque_nm double precision,
    force_n double precision,
    radial_depth_mm double precision,
    axial_depth_mm double precision,
    depth_status text,
    feed_override_pct double precision,
    program bigint,
    tool bigint,
    operation integer,
    process_rev bigint
);


--
-- Name: schema_version; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.schema_version (
    version integer NOT NULL,
    since timestamp with time zone DEFAULT now() NOT NULL
);


--
-- Name: status_changes; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.status_changes (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    state text,
    daq_link text,
    interlock text,
    alarm text,
    faults jsonb,
    run_id text,
    payload jsonb NOT NULL
)
PARTITION BY RANGE ("time");


--
-- Name: status_changes_default; Type: TABLE; Schema: public; Owner: -
--

CREATE TABLE public.status_changes_default (
    "time" timestamp with time zone NOT NULL,
    received_at timestamp with time zone NOT NULL,
    machine text NOT NULL,
    state text,
    daq_link text,
    interlock text,
    alarm text,
    faults jsonb,
    run_id text,
    payload jsonb NOT NULL
);


--
-- Name: alarms_default; Type: TABLE ATTACH; Schema: public; Owner: -
--

ALTER TABLE ONLY public.alarms ATTACH PARTITION public.alarms_default DEFAULT;


--
-- Name: limit_changes_default; Type: TABLE ATTACH; Schema: public; Owner: -
--

ALTER TABLE ONLY public.limit_changes ATTACH PARTITION public.limit_changes_default DEFAULT;


--
-- Name: limit_changes_p20261120; Type: TABLE ATTACH; Schema: public; Owner: -
--

ALTER TABLE ONLY public.limit_changes ATTACH PARTITION public.limit_changes_p20261120 FOR VALUES FROM ('2026-11-20 00:00:00+00') TO ('2026-11-21 00:00:00+00');


--
-- Name: load_1s_default; Type: TABLE ATTACH; Schema: public; Owner: -
--

ALTER TABLE ONLY public.load_1s ATTACH PARTITION public.load_1s_default DEFAULT;


--
-- Name: processes_default; Type: TABLE ATTACH; Schema: public; Owner: -
--

ALTER TABLE ONLY public.processes ATTACH PARTITION public.processes_default DEFAULT;


--
-- Name: revolutions_default; Type: TABLE ATTACH; Schema: public; Owner: -
--

ALTER TABLE ONLY public.revolutions ATTACH PARTITION public.revolutions_default DEFAULT;


--
-- Name: status_changes_default; Type: TABLE ATTACH; Schema: public; Owner: -
--

ALTER TABLE ONLY public.status_changes ATTACH PARTITION public.status_changes_default DEFAULT;


--
-- Data for Name: alarms_default; Type: TABLE DATA; Schema: public; Owner: -
--

COPY public.alarms_default ("time", received_at, machine, level, quantity, value, limit_value, interlock, rev, run_id, alarm_seq, program, tool, operation, process, process_rev, expected, reason, payload) FROM stdin;
\.


--
-- Data for Name: limit_changes_default; Type: TABLE DATA; Schema: public; Owner: -
--

COPY public.limit_changes_default ("time", received_at, machine, key, change, envelope, learned, process) FROM stdin;
\.


--
-- Data for Name: limit_changes_p20261120; Type: TABLE DATA; Schema: public; Owner: -
--

COPY public.limit_changes_p20261120 ("time", received_at, machine, key, change, envelope, learned, process) FROM stdin;
2026-11-20 08:00:00+00	2026-11-20 08:00:01+00	mch-v1	1234/12/3	learning->pending	pending	5	41
\.


--
-- Data for Name: load_1s_default; Type: TABLE DATA; Schema: public; Owner: -
--

COPY public.load_1s_default ("time", received_at, machine, revolutions, valid, invalid, torque_min_nm, torque_mean_nm, torque_max_nm, force_min_n, force_mean_n, force_max_n, power_min_w, power_mean_w, power_max_w) FROM stdin;
\.


--
-- Data for Name: processes_default; Type: TABLE DATA; Schema: public; Owner: -
--

COPY public.processes_default ("time", received_at, machine, process, key, program, tool, operation, revolutions, cutting_revolutions, entry_rev, torque_peak_nm, torque_mean_nm, force_peak_n, energy_j, verdict, learned, learn_target, envelope, energy_ratio, tool_processes, tool_wear_pct, expected_band, payload) FROM stdin;
\.


--
-- Data for Name: revolutions_default; Type: TABLE DATA; Schema: public; Owner: -
--

COPY public.revolutions_default ("time", received_at, machine, rev, valid, invalid, spindle_rpm, p_in_w, p_gap_w, torque_nm, force_n, radial_depth_mm, axial_depth_mm, depth_status, feed_override_pct, program, tool, operation, process_rev) FROM stdin;
\.


--
-- Data for Name: schema_version; Type: TABLE DATA; Schema: public; Owner: -
--

COPY public.schema_version (version, since) FROM stdin;
1	2026-11-29 11:25:37.232657+00
\.


--
-- Data for Name: status_changes_default; Type: TABLE DATA; Schema: public; Owner: -
--

COPY public.status_changes_default ("time", received_at, machine, state, daq_link, interlock, alarm, faults, run_id, payload) FROM stdin;
\.


--
-- Name: alarms alarms_machine_time_level_quantity_alarm_seq_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.alarms
    ADD CONSTRAINT alarms_machine_time_level_quantity_alarm_seq_key UNIQUE NULLS NOT DISTINCT (machine, "time", level, quantity, alarm_seq);


--
-- Name: alarms_default alarms_default_machine_time_level_quantity_alarm_seq_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.alarms_default
    ADD CONSTRAINT alarms_default_machine_time_level_quantity_alarm_seq_key UNIQUE NULLS NOT DISTINCT (machine, "time", level, quantity, alarm_seq);


--
-- Name: limit_changes limit_changes_machine_time_key_change_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.limit_changes
    ADD CONSTRAINT limit_changes_machine_time_key_change_key UNIQUE NULLS NOT DISTINCT (machine, "time", key, change);


--
-- Name: limit_changes_default limit_changes_default_machine_time_key_change_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.limit_changes_default
    ADD CONSTRAINT limit_changes_default_machine_time_key_change_key UNIQUE NULLS NOT DISTINCT (machine, "time", key, change);


--
-- Name: limit_changes_p20261120 limit_changes_p20261120_machine_time_key_change_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.limit_changes_p20261120
    ADD CONSTRAINT limit_changes_p20261120_machine_time_key_change_key UNIQUE NULLS NOT DISTINCT (machine, "time", key, change);


--
-- Name: load_1s load_1s_machine_time_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.load_1s
    ADD CONSTRAINT load_1s_machine_time_key UNIQUE NULLS NOT DISTINCT (machine, "time");


--
-- Name: load_1s_default load_1s_default_machine_time_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.load_1s_default
    ADD CONSTRAINT load_1s_default_machine_time_key UNIQUE NULLS NOT DISTINCT (machine, "time");


--
-- Name: processes processes_machine_time_process_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.processes
    ADD CONSTRAINT processes_machine_time_process_key UNIQUE NULLS NOT DISTINCT (machine, "time", process);


--
-- Name: processes_default processes_default_machine_time_process_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.processes_default
    ADD CONSTRAINT processes_default_machine_time_process_key UNIQUE NULLS NOT DISTINCT (machine, "time", process);


--
-- Name: revolutions revolutions_machine_time_rev_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.revolutions
    ADD CONSTRAINT revolutions_machine_time_rev_key UNIQUE NULLS NOT DISTINCT (machine, "time", rev);


--
-- Name: revolutions_default revolutions_default_machine_time_rev_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.revolutions_default
    ADD CONSTRAINT revolutions_default_machine_time_rev_key UNIQUE NULLS NOT DISTINCT (machine, "time", rev);


--
-- Name: status_changes status_changes_machine_time_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.status_changes
    ADD CONSTRAINT status_changes_machine_time_key UNIQUE NULLS NOT DISTINCT (machine, "time");


--
-- Name: status_changes_default status_changes_default_machine_time_key; Type: CONSTRAINT; Schema: public; Owner: -
--

ALTER TABLE ONLY public.status_changes_default
    ADD CONSTRAINT status_changes_default_machine_time_key UNIQUE NULLS NOT DISTINCT (machine, "time");


--
-- Name: alarms_i0; Type: INDEX; Schema: public; Owner: -
--

CREATE INDEX alarms_i0 ON ONLY public.alarms USING btree (level, "time");


--
-- Name: alarms_default_level_time_idx; Type: INDEX; Schema: public; Owner: -
--

CREATE INDEX alarms_default_level_time_idx ON public.alarms_default USING btree (level, "time");


--
-- Name: processes_i0; Type: INDEX; Schema: public; Owner: -
--

CREATE INDEX processes_i0 ON ONLY public.processes USING btree (program, tool, operation, "time");


--
-- Name: processes_default_program_tool_operation_time_idx; Type: INDEX; Schema: public; Owner: -
--

CREATE INDEX processes_default_program_tool_operation_time_idx ON public.processes_default USING btree (program, tool, operation, "time");


--
-- Name: alarms_default_level_time_idx; Type: INDEX ATTACH; Schema: public; Owner: -
--

ALTER INDEX public.alarms_i0 ATTACH PARTITION public.alarms_default_level_time_idx;


--
-- Name: alarms_default_machine_time_level_quantity_alarm_seq_key; Type: INDEX ATTACH; Schema: public; Owner: -
--

ALTER INDEX public.alarms_machine_time_level_quantity_alarm_seq_key ATTACH PARTITION public.alarms_default_machine_time_level_quantity_alarm_seq_key;


--
-- Name: limit_changes_default_machine_time_key_change_key; Type: INDEX ATTACH; Schema: public; Owner: -
--

ALTER INDEX public.limit_changes_machine_time_key_change_key ATTACH PARTITION public.limit_changes_default_machine_time_key_change_key;


--
-- Name: limit_changes_p20261120_machine_time_key_change_key; Type: INDEX ATTACH; Schema: public; Owner: -
--

ALTER INDEX public.limit_changes_machine_time_key_change_key ATTACH PARTITION public.limit_changes_p20261120_machine_time_key_change_key;


--
-- Name: load_1s_default_machine_time_key; Type: INDEX ATTACH; Schema: public; Owner: -
--

ALTER INDEX public.load_1s_machine_time_key ATTACH PARTITION public.load_1s_default_machine_time_key;


--
-- Name: processes_default_machine_time_process_key; Type: INDEX ATTACH; Schema: public; Owner: -
--

ALTER INDEX public.processes_machine_time_process_key ATTACH PARTITION public.processes_default_machine_time_process_key;


--
-- Name: processes_default_program_tool_operation_time_idx; Type: INDEX ATTACH; Schema: public; Owner: -
--

ALTER INDEX public.processes_i0 ATTACH PARTITION public.processes_default_program_tool_operation_time_idx;


--
-- Name: revolutions_default_machine_time_rev_key; Type: INDEX ATTACH; Schema: public; Owner: -
--

ALTER INDEX public.revolutions_machine_time_rev_key ATTACH PARTITION public.revolutions_default_machine_time_rev_key;


--
-- Name: status_changes_default_machine_time_key; Type: INDEX ATTACH; Schema: public; Owner: -
--

ALTER INDEX public.status_changes_machine_time_key ATTACH PARTITION public.status_changes_default_machine_time_key;


--
-- PostgreSQL database dump complete
--

\unrestrict G1ZSU1opilveOArlFNvOgC44gEsIVjT15CSupF5kE5KOcvWvE1Pfks1pk0Cx3C1

