/*
 * msfw-host: the firmware core on a POSIX host, as a board. Its "ADC" plays a
 * capture of the plant simulator (`millsense sim --capture`), one sample set a
 * tick on the monotonic clock; its link is a TCP server (one client: the newest
 * connection wins) or a pseudo-terminal; its outputs and counters are JSON lines
 * in a log, so tests wait on the device's own events.
 *
 * This file is the board, not the firmware: it may use libc. The firmware core
 * is src/ms_core.c and src/ms_frame.c, the same files the Cortex-M build compiles.
 */
#define _GNU_SOURCE
#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "msfw.h"

/* ---- options ------------------------------------------------------------ */
static const char *opt_capture, *opt_tcp, *opt_pty, *opt_log, *opt_modbus_tcp, *opt_modbus_rtu;
static long opt_unit = 1;
static long opt_watchdog_ms, opt_ring = 1024, opt_per_frame = 10, opt_skip, opt_start_index;
static long opt_sndbuf, opt_cnc_hold_lag_ms = 30;
static int opt_wait_client, opt_hold_until_heartbeat, opt_once;

/* ---- the capture: the plant's samples and the CNC's context ---------------- */
typedef struct { long pos; ms_cnc cnc; } cap_ctx;
static ms_config cfg;
static int16_t *cap_samples;
static long cap_n;          /* samples in the capture */
static cap_ctx *cap_ctxs;
static long cap_nctx;
static int cap_has_context;

/* ---- the board's state ------------------------------------------------------ */
static ms_device dev;
static long play_pos;       /* the capture's next sample */
static long ctx_next;       /* the next context change to play */
static ms_cnc cnc_now;      /* the CNC's inputs now */
static uint8_t out_now;
static uint16_t override_now = MS_OVERRIDE_NEUTRAL;
static int cnc_held, cnc_held_target;
static double cnc_held_due = -1.0;
static FILE *logf;
static int listen_fd = -1, client_fd = -1, pty_master = -1, pty_slave = -1;
static volatile sig_atomic_t stop_flag, restart_flag;
static struct timespec t0;
static uint64_t ticks;
static int started;
static double last_heartbeat_mono = -1.0;
static uint8_t mb_buf[MS_MODBUS_MAX_ADU];
static size_t mb_len;
static ms_counters logged_counters;
static double counters_logged_at;

static double mono_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

static double wall_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

static void logj(const char *event, const char *fmt, ...)
{
    if (logf == NULL) {
        return;
    }
    fprintf(logf, "{\"event\": \"%s\", \"mono\": %.6f, \"wall\": %.6f, \"index\": %u", event, mono_s(), wall_s(),
            (unsigned)dev.head);
    if (fmt != NULL && fmt[0] != '\0') {
        va_list ap;
        va_start(ap, fmt);
        fputs(", ", logf);
        vfprintf(logf, fmt, ap);
        va_end(ap);
    }
    fputs("}\n", logf);
    fflush(logf);
}

static void log_counters(const char *event)
{
    const ms_counters *n = &dev.n;
    logj(event,
         "\"bad_frames\": %u, \"skipped_bytes\": %u, \"bad_commands\": %u, \"commands\": %u, "
         "\"overrun_samples\": %u, \"overrun_events\": %u, \"override_refused\": %u, \"watchdog_trips\": %u, "
         "\"frames_sent\": %u",
         n->bad_frames, n->skipped_bytes, n->bad_commands, n->commands, n->overrun_samples, n->overrun_events,
         n->override_refused, n->watchdog_trips, n->frames_sent);
    logged_counters = *n;
    counters_logged_at = mono_s();
}

static const char *cause_name(uint32_t c)
{
    switch (c) {
    case MS_CAUSE_INIT: return "restart";
    case MS_CAUSE_COMMAND: return "command";
    case MS_CAUSE_WATCHDOG: return "watchdog";
    case MS_CAUSE_HEARTBEAT: return "heartbeat";
    default: return "?";
    }
}

/* ---- the hardware interface ------------------------------------------------ */

void ms_hw_read_sample(int16_t *counts)
{
    const int16_t *src = &cap_samples[(size_t)play_pos * cfg.channel_count];
    memcpy(counts, src, sizeof(int16_t) * cfg.channel_count);
    play_pos++;
    if (play_pos >= cap_n) {
        play_pos = opt_skip; /* the plant plays on from the start (opt_once: the loop ends, see main) */
        ctx_next = 0;
    }
    while (ctx_next < cap_nctx && cap_ctxs[ctx_next].pos <= play_pos) {
        uint8_t held = (uint8_t)(cnc_now.flags & MS_CTX_FEED_HELD);
        cnc_now = cap_ctxs[ctx_next++].cnc;
        cnc_now.flags = (uint8_t)((cnc_now.flags & (uint8_t)~MS_CTX_FEED_HELD) | held);
    }
}

void ms_hw_write_outputs(uint8_t outputs)
{
    out_now = outputs;
    int held = (outputs & MS_OUT_FEED_HOLD) != 0;
    if (held != cnc_held_target) {
        /* the CNC answers its feed-hold input after its own scan time */
        cnc_held_target = held;
        cnc_held_due = mono_s() + (double)opt_cnc_hold_lag_ms / 1000.0;
    }
}

void ms_hw_write_override(uint16_t tenths) { override_now = tenths; }

void ms_hw_read_cnc(ms_cnc *cnc)
{
    if (cnc_held_due >= 0.0 && mono_s() >= cnc_held_due) {
        cnc_held_due = -1.0;
        if (cnc_held != cnc_held_target) {
            cnc_held = cnc_held_target;
            logj("cnc_feed_held", "\"feed_held\": %s", cnc_held ? "true" : "false");
        }
    }
    *cnc = cnc_now;
    cnc->flags = (uint8_t)((cnc->flags & (uint8_t)~MS_CTX_FEED_HELD) | (cnc_held ? MS_CTX_FEED_HELD : 0u));
    cnc->override_applied = MS_OVERRIDE_NO_READBACK; /* no PLC to read it back from: STATUS says the commanded one */
}

static void close_client(const char *why)
{
    if (client_fd >= 0) {
        close(client_fd);
        client_fd = -1;
        logj("client", "\"state\": \"closed\", \"why\": \"%s\"", why);
    }
}

size_t ms_hw_tx(const uint8_t *data, size_t n)
{
    int fd = client_fd >= 0 ? client_fd : pty_master;
    if (fd < 0) {
        return n; /* nobody listening: the bytes go onto a line with no reader */
    }
    ssize_t w = fd == client_fd ? send(fd, data, n, MSG_NOSIGNAL | MSG_DONTWAIT) : write(fd, data, n);
    if (w < 0) {
        if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) {
            return 0; /* back-pressure: the core keeps the rest and its ring fills */
        }
        if (fd == client_fd) {
            close_client(strerror(errno));
        }
        return n;
    }
    return (size_t)w;
}

size_t ms_hw_rx(uint8_t *data, size_t max)
{
    int fd = client_fd >= 0 ? client_fd : pty_master;
    if (fd < 0 || max == 0) {
        return 0;
    }
    ssize_t r = fd == client_fd ? recv(fd, data, max, MSG_DONTWAIT) : read(fd, data, max);
    if (r > 0) {
        return (size_t)r;
    }
    if (r == 0 && fd == client_fd) {
        close_client("eof");
    } else if (r < 0 && fd == client_fd && errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) {
        close_client(strerror(errno));
    }
    return 0;
}

uint32_t ms_hw_millis(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint32_t)((uint64_t)ts.tv_sec * 1000u + (uint64_t)ts.tv_nsec / 1000000u);
}

void ms_hw_event(ms_event ev, uint32_t a, uint32_t b)
{
    double now = mono_s();
    switch (ev) {
    case MS_EV_RESTART:
        logj("restart", "\"first_index\": %u", a);
        break;
    case MS_EV_OUTPUTS:
        logj("outputs", "\"outputs\": %u, \"feed_hold\": %s, \"alarm_lamp\": %s, \"watchdog\": %s, \"cause\": \"%s\"", a,
             (a & 1u) ? "true" : "false", (a & 2u) ? "true" : "false",
             (dev.flags & MS_FLAG_WATCHDOG) ? "true" : "false", cause_name(b));
        break;
    case MS_EV_OVERRIDE:
        logj("feed_override", "\"value\": %u, \"cause\": \"%s\"", a, cause_name(b));
        break;
    case MS_EV_OVERRIDE_REFUSED:
        logj("feed_override_refused", "\"value\": %u, \"why\": \"%s\"", a,
             b == MS_REFUSE_RANGE ? "range" : b == MS_REFUSE_WATCHDOG ? "watchdog" : "no_output");
        break;
    case MS_EV_HEARTBEAT:
        last_heartbeat_mono = now;
        logj("heartbeat", "\"counter\": %u", a);
        break;
    case MS_EV_WATCHDOG:
        logj("watchdog", "\"last_heartbeat_mono\": %.6f, \"last_heartbeat_ms\": %u, \"now_ms\": %u", last_heartbeat_mono,
             a, b);
        break;
    case MS_EV_COMMAND:
        if (a != MS_CMD_HEARTBEAT) { /* ten a second: the heartbeat event says what matters */
            logj("command", "\"command\": %u, \"argument\": %u", a, b);
        }
        break;
    case MS_EV_BAD_FRAME:
        logj("bad_frame", "\"bad_frames\": %u, \"skipped_bytes\": %u", a, b);
        break;
    case MS_EV_BAD_COMMAND:
        logj("bad_command", "\"bad_commands\": %u, \"command\": %u", a, b);
        break;
    case MS_EV_OVERRUN:
        if (dev.n.overrun_events <= 1u || now - counters_logged_at >= 0.1) { /* at most ten lines a second */
            logj("overrun", "\"lost\": %u, \"overrun_samples\": %u", a, b);
            log_counters("counters");
        }
        break;
    case MS_EV_WATCHDOG_PERIOD:
        logj("watchdog_period", "\"watchdog_ms\": %u", a);
        break;
    case MS_EV_CONTEXT:
        logj("context", "\"from_index\": %u, \"flags\": %u", a, b);
        break;
    }
}

/* ---- reading the capture (with the core's own CRC) -------------------------------- */

static int read_capture(const char *path)
{
    FILE *f = fopen(path, "rb");
    if (f == NULL) {
        fprintf(stderr, "msfw-host: error: cannot read capture %s: %s\n", path, strerror(errno));
        return -1;
    }
    fseek(f, 0, SEEK_END);
    long size = ftell(f);
    fseek(f, 0, SEEK_SET);
    uint8_t *buf = malloc((size_t)size + 1u);
    if (buf == NULL || fread(buf, 1, (size_t)size, f) != (size_t)size) {
        fprintf(stderr, "msfw-host: error: cannot read capture %s\n", path);
        fclose(f);
        return -1;
    }
    fclose(f);
    int have_desc = 0;
    long cap_alloc = 0, ctx_alloc = 0;
    long first_index = -1;
    long i = 0;
    while (i + 7 <= size) {
        if (buf[i] != MS_SYNC0 || buf[i + 1] != MS_SYNC1) {
            i++;
            continue;
        }
        uint8_t type = buf[i + 2];
        long len = buf[i + 3] | (buf[i + 4] << 8);
        if (len > (long)MS_MAX_PAYLOAD || i + 7 + len > size) {
            i++;
            continue;
        }
        uint16_t crc = ms_crc16(MS_CRC_INIT, &buf[i + 2], 3u + (size_t)len);
        if ((crc & 0xFF) != buf[i + 5 + len] || (crc >> 8) != buf[i + 6 + len]) {
            i++;
            continue;
        }
        const uint8_t *p = &buf[i + 5];
        if (type == MS_T_DESCRIPTOR && !have_desc && len >= 4) {
            cfg.sample_rate_hz = (uint16_t)(p[1] | (p[2] << 8));
            cfg.channel_count = p[3];
            if (cfg.channel_count == 0 || cfg.channel_count > MS_MAX_CHANNELS || len < 4 + 9 * (long)p[3]) {
                fprintf(stderr, "msfw-host: error: capture %s: %u channels (this build takes 1..%u)\n", path,
                        p[3], (unsigned)MS_MAX_CHANNELS);
                return -1;
            }
            for (int c = 0; c < cfg.channel_count; c++) {
                cfg.channels[c].kind = p[4 + 9 * c];
                memcpy(cfg.channels[c].name, &p[5 + 9 * c], 8);
            }
            if (p[0] >= 2 && len >= 5 + 9 * (long)p[3] && (p[4 + 9 * p[3]] & MS_CAP_CONTEXT)) {
                cap_has_context = 1;
            }
            have_desc = 1;
        } else if (type == MS_T_SAMPLES && have_desc && len >= 6 && p[4] == cfg.channel_count &&
                   len == 6 + 2L * p[4] * p[5]) {
            long idx = (long)((uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24));
            if (first_index < 0) {
                first_index = idx;
            }
            for (int s = 0; s < p[5]; s++) {
                if (cap_n == cap_alloc) {
                    cap_alloc = cap_alloc ? cap_alloc * 2 : 65536;
                    cap_samples = realloc(cap_samples, (size_t)cap_alloc * cfg.channel_count * sizeof(int16_t));
                }
                for (int c = 0; c < cfg.channel_count; c++) {
                    const uint8_t *q = &p[6 + 2 * (s * cfg.channel_count + c)];
                    cap_samples[(size_t)cap_n * cfg.channel_count + (size_t)c] = (int16_t)(uint16_t)(q[0] | (q[1] << 8));
                }
                cap_n++;
            }
        } else if (type == MS_T_CONTEXT && len >= 15) {
            if (cap_nctx == ctx_alloc) {
                ctx_alloc = ctx_alloc ? ctx_alloc * 2 : 64;
                cap_ctxs = realloc(cap_ctxs, (size_t)ctx_alloc * sizeof *cap_ctxs);
            }
            uint32_t idx = (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
            cap_ctx *e = &cap_ctxs[cap_nctx++];
            e->pos = first_index < 0 ? 0 : (long)(idx - (uint32_t)first_index);
            e->cnc.program = (uint32_t)p[4] | ((uint32_t)p[5] << 8) | ((uint32_t)p[6] << 16) | ((uint32_t)p[7] << 24);
            e->cnc.tool = (uint32_t)p[8] | ((uint32_t)p[9] << 8) | ((uint32_t)p[10] << 16) | ((uint32_t)p[11] << 24);
            e->cnc.operation = (uint16_t)(p[12] | (p[13] << 8));
            e->cnc.flags = p[14];
            cap_has_context = 1;
        }
        i += 7 + len;
    }
    free(buf);
    if (!have_desc || cap_n == 0) {
        fprintf(stderr, "msfw-host: error: capture %s has no DESCRIPTOR and SAMPLES\n", path);
        return -1;
    }
    if (opt_skip >= cap_n) {
        fprintf(stderr, "msfw-host: error: --skip %ld: the capture has %ld samples\n", opt_skip, cap_n);
        return -1;
    }
    return 0;
}

/* ---- the link --------------------------------------------------------------------- */

static int open_tcp(const char *spec)
{
    char host[128];
    const char *colon = strrchr(spec, ':');
    if (colon == NULL || (size_t)(colon - spec) >= sizeof host) {
        fprintf(stderr, "msfw-host: error: --tcp: expected HOST:PORT, got %s\n", spec);
        return -1;
    }
    memcpy(host, spec, (size_t)(colon - spec));
    host[colon - spec] = '\0';
    struct sockaddr_in a;
    memset(&a, 0, sizeof a);
    a.sin_family = AF_INET;
    a.sin_port = htons((uint16_t)atoi(colon + 1));
    if (inet_pton(AF_INET, host, &a.sin_addr) != 1) {
        fprintf(stderr, "msfw-host: error: --tcp: not an IPv4 address: %s\n", host);
        return -1;
    }
    listen_fd = socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    int one = 1;
    setsockopt(listen_fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    if (bind(listen_fd, (struct sockaddr *)&a, sizeof a) != 0 || listen(listen_fd, 4) != 0) {
        fprintf(stderr, "msfw-host: error: cannot listen on %s: %s\n", spec, strerror(errno));
        return -1;
    }
    return 0;
}

static void start_clock(void)
{
    clock_gettime(CLOCK_MONOTONIC, &t0);
    ticks = 0;
    started = 1;
    logj("start", "\"first_index\": %u, \"capture_first\": %ld, \"sample_rate_hz\": %u, \"channels\": %u, "
                  "\"watchdog_ms\": %ld, \"ring_samples\": %u", (unsigned)dev.head, play_pos, cfg.sample_rate_hz,
         cfg.channel_count, opt_watchdog_ms, cfg.ring_samples);
}

static void accept_client(void)
{
    int fd = accept4(listen_fd, NULL, NULL, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) {
        return;
    }
    close_client("replaced"); /* the newest connection wins: a restarted daemon finds the board free */
    int one = 1;
    setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    if (opt_sndbuf > 0) {
        int sz = (int)opt_sndbuf;
        setsockopt(fd, SOL_SOCKET, SO_SNDBUF, &sz, sizeof sz);
    }
    client_fd = fd;
    mb_len = 0;
    ms_link_reset(&dev); /* each client gets the stream from its connect on, a DESCRIPTOR first */
    logj("client", "\"state\": \"connected\"");
    if (!started) {
        start_clock();
    }
}

static int open_pty(const char *link)
{
    pty_master = posix_openpt(O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
    if (pty_master < 0 || grantpt(pty_master) != 0 || unlockpt(pty_master) != 0) {
        fprintf(stderr, "msfw-host: error: no pseudo-terminal: %s\n", strerror(errno));
        return -1;
    }
    const char *name = ptsname(pty_master);
    pty_slave = open(name, O_RDWR | O_NOCTTY | O_CLOEXEC); /* kept open: a reader that closes is no hang-up */
    struct termios t;
    if (pty_slave < 0 || tcgetattr(pty_slave, &t) != 0) {
        fprintf(stderr, "msfw-host: error: cannot open %s: %s\n", name, strerror(errno));
        return -1;
    }
    cfmakeraw(&t);
    tcsetattr(pty_slave, TCSANOW, &t);
    char tmp[4096];
    snprintf(tmp, sizeof tmp, "%s.tmp%d", link, (int)getpid());
    unlink(tmp);
    if (symlink(name, tmp) != 0 || rename(tmp, link) != 0) {
        fprintf(stderr, "msfw-host: error: cannot make the pty link %s: %s\n", link, strerror(errno));
        return -1;
    }
    return 0;
}

/* Modbus TCP: whole ADUs out of the client's bytes, each answered by the core's register map. */
static void serve_modbus(void)
{
    if (client_fd < 0) {
        return;
    }
    for (;;) {
        ssize_t r = recv(client_fd, &mb_buf[mb_len], sizeof mb_buf - mb_len, MSG_DONTWAIT);
        if (r == 0) {
            close_client("eof");
            return;
        }
        if (r < 0) {
            if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) {
                close_client(strerror(errno));
            }
            return;
        }
        mb_len += (size_t)r;
        while (mb_len >= 7) {
            size_t len = ((size_t)mb_buf[4] << 8) | mb_buf[5];
            if (len < 2 || len > sizeof mb_buf - 6) {
                close_client("not Modbus TCP");
                mb_len = 0;
                return;
            }
            if (mb_len < 6 + len) {
                break;
            }
            uint8_t out[MS_MODBUS_MAX_ADU];
            size_t n = ms_modbus_tcp(&dev, (uint8_t)opt_unit, mb_buf, 6 + len, out, sizeof out);
            if (n > 0 && send(client_fd, out, n, MSG_NOSIGNAL) != (ssize_t)n) {
                close_client("send");
                mb_len = 0;
                return;
            }
            memmove(mb_buf, &mb_buf[6 + len], mb_len - (6 + len));
            mb_len -= 6 + len;
        }
    }
}

/* Modbus RTU on a pty: a pty has no character timing, so a request is delimited by its length, which its
 * function code gives (8 bytes for 1-6; 9 + the byte count for 15 and 16). A frame whose CRC fails drops one
 * byte and the next is tried, as a receiver that lost the silence would. The core answers or stays silent. */
static uint8_t rtu_buf[2 * MS_MODBUS_MAX_ADU];
static size_t rtu_len;

static size_t rtu_frame_length(const uint8_t *b, size_t n)
{
    if (n < 2) {
        return 0;
    }
    if (b[1] >= 1 && b[1] <= 6) {
        return 8;
    }
    if (b[1] == 15 || b[1] == 16) {
        return n < 7 ? 0 : 9u + b[6];
    }
    return 1; /* no request this board knows: resynchronise */
}

static void serve_modbus_rtu(void)
{
    for (;;) {
        ssize_t r = read(pty_master, &rtu_buf[rtu_len], sizeof rtu_buf - rtu_len);
        if (r <= 0) {
            return;
        }
        rtu_len += (size_t)r;
        for (;;) {
            size_t need = rtu_frame_length(rtu_buf, rtu_len);
            if (need == 0 || rtu_len < need) {
                break;
            }
            size_t used = need;
            if (need >= 4) {
                uint16_t crc = ms_crc16(MS_CRC_INIT, rtu_buf, need - 2);
                if ((crc & 0xFF) != rtu_buf[need - 2] || (crc >> 8) != rtu_buf[need - 1]) {
                    used = 1;
                } else {
                    uint8_t out[MS_MODBUS_MAX_ADU];
                    size_t n = ms_modbus_rtu(&dev, (uint8_t)opt_unit, rtu_buf, need, out, sizeof out);
                    if (n > 0 && write(pty_master, out, n) != (ssize_t)n) {
                        logj("modbus_rtu", "\"dropped_reply\": %zu", n);
                    }
                }
            }
            memmove(rtu_buf, &rtu_buf[used], rtu_len - used);
            rtu_len -= used;
        }
        if (rtu_len == sizeof rtu_buf) {
            rtu_len = 0; /* cannot happen with whole requests; never stall on garbage */
        }
    }
}

/* ---- main ---------------------------------------------------------------------------- */

static void on_signal(int sig)
{
    if (sig == SIGUSR1) {
        restart_flag = 1;
    } else {
        stop_flag = 1;
    }
}

static void usage(void)
{
    fprintf(stderr,
            "usage: msfw-host --capture FILE (--tcp HOST:PORT | --pty LINK | --modbus-tcp HOST:PORT | --modbus-rtu LINK)\n"
            "       [--unit N]\n"
            "       [--log FILE] [--watchdog-ms MS]\n"
            "       [--ring SAMPLES] [--per-frame N] [--skip SAMPLES] [--start-index N] [--wait-client] [--once]\n"
            "       [--hold-until-heartbeat] [--cnc-hold-lag-ms MS] [--sndbuf BYTES]\n"
            "SIGUSR1 restarts the firmware core (as a board reset would); SIGTERM stops.\n");
}

static int parse_long(const char *s, long lo, long hi, long *out, const char *what)
{
    char *end;
    errno = 0;
    long v = strtol(s, &end, 10);
    if (errno != 0 || *end != '\0' || v < lo || v > hi) {
        fprintf(stderr, "msfw-host: error: %s: expected a whole number within %ld..%ld, got %s\n", what, lo, hi, s);
        return -1;
    }
    *out = v;
    return 0;
}

static int configure(void)
{
    cfg.link = (opt_modbus_tcp || opt_modbus_rtu) ? MS_LINK_MODBUS : MS_LINK_STREAM;
    cfg.capabilities = (uint8_t)(MS_CAP_OVERRIDE | (cap_has_context ? MS_CAP_CONTEXT : 0u));
    cfg.ring_samples = (uint16_t)opt_ring;
    cfg.samples_per_frame = (uint8_t)opt_per_frame;
    cfg.watchdog_ms = (uint16_t)opt_watchdog_ms;
    cfg.descriptor_period_ms = 1000;
    cfg.start_index = (uint32_t)opt_start_index;
    cfg.hold_until_heartbeat = opt_hold_until_heartbeat != 0;
    if (ms_init(&dev, &cfg) != 0) {
        fprintf(stderr, "msfw-host: error: the core refuses this config (--ring a power of two 2..%u, above "
                        "--per-frame 1..64)\n", (unsigned)MS_RING_SAMPLES);
        return -1;
    }
    return 0;
}

int main(int argc, char **argv)
{
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
#define VAL() do { if (v == NULL) { fprintf(stderr, "msfw-host: error: %s needs a value\n", a); return 2; } i++; } while (0)
        if (!strcmp(a, "--capture")) { VAL(); opt_capture = v; }
        else if (!strcmp(a, "--tcp")) { VAL(); opt_tcp = v; }
        else if (!strcmp(a, "--pty")) { VAL(); opt_pty = v; }
        else if (!strcmp(a, "--modbus-tcp")) { VAL(); opt_modbus_tcp = v; }
        else if (!strcmp(a, "--modbus-rtu")) { VAL(); opt_modbus_rtu = v; }
        else if (!strcmp(a, "--unit")) { VAL(); if (parse_long(v, 1, 247, &opt_unit, a)) return 2; }
        else if (!strcmp(a, "--log")) { VAL(); opt_log = v; }
        else if (!strcmp(a, "--watchdog-ms")) { VAL(); if (parse_long(v, 0, 65535, &opt_watchdog_ms, a)) return 2; }
        else if (!strcmp(a, "--ring")) { VAL(); if (parse_long(v, 2, MS_RING_SAMPLES, &opt_ring, a)) return 2; }
        else if (!strcmp(a, "--per-frame")) { VAL(); if (parse_long(v, 1, 64, &opt_per_frame, a)) return 2; }
        else if (!strcmp(a, "--skip")) { VAL(); if (parse_long(v, 0, 1L << 30, &opt_skip, a)) return 2; }
        else if (!strcmp(a, "--start-index")) { VAL(); if (parse_long(v, 0, 4294967295L, &opt_start_index, a)) return 2; }
        else if (!strcmp(a, "--sndbuf")) { VAL(); if (parse_long(v, 0, 1L << 26, &opt_sndbuf, a)) return 2; }
        else if (!strcmp(a, "--cnc-hold-lag-ms")) { VAL(); if (parse_long(v, 0, 10000, &opt_cnc_hold_lag_ms, a)) return 2; }
        else if (!strcmp(a, "--wait-client")) { opt_wait_client = 1; }
        else if (!strcmp(a, "--once")) { opt_once = 1; }
        else if (!strcmp(a, "--hold-until-heartbeat")) { opt_hold_until_heartbeat = 1; }
        else if (!strcmp(a, "--help") || !strcmp(a, "-h")) { usage(); return 0; }
        else { fprintf(stderr, "msfw-host: error: unknown option %s\n", a); usage(); return 2; }
#undef VAL
    }
    if (opt_capture == NULL ||
        (opt_tcp != NULL) + (opt_pty != NULL) + (opt_modbus_tcp != NULL) + (opt_modbus_rtu != NULL) != 1) {
        fprintf(stderr, "msfw-host: error: give --capture and one of --tcp, --pty, --modbus-tcp, --modbus-rtu\n");
        usage();
        return 2;
    }
    if (opt_log != NULL && (logf = fopen(opt_log, "a")) == NULL) {
        fprintf(stderr, "msfw-host: error: cannot open log %s: %s\n", opt_log, strerror(errno));
        return 1;
    }
    if (read_capture(opt_capture) != 0) {
        return 1;
    }
    play_pos = opt_skip;
    while (ctx_next < cap_nctx && cap_ctxs[ctx_next].pos <= play_pos) {
        cnc_now = cap_ctxs[ctx_next++].cnc;
    }
    if (configure() != 0) {
        return 2;
    }
    if ((opt_tcp && open_tcp(opt_tcp) != 0) || (opt_modbus_tcp && open_tcp(opt_modbus_tcp) != 0) ||
        (opt_pty && open_pty(opt_pty) != 0) || (opt_modbus_rtu && open_pty(opt_modbus_rtu) != 0)) {
        return 1;
    }
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGUSR1, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);
    fprintf(stderr, "msfw-host: serving %ld samples of %u channels at %u Hz on %s %s\n", cap_n, cfg.channel_count,
            cfg.sample_rate_hz, opt_tcp ? "tcp" : opt_pty ? "pty" : opt_modbus_tcp ? "modbus-tcp" : "modbus-rtu",
            opt_tcp ? opt_tcp : opt_pty ? opt_pty : opt_modbus_tcp ? opt_modbus_tcp : opt_modbus_rtu);
    if (!opt_wait_client || opt_pty || opt_modbus_rtu) {
        start_clock();
    }
    const double period_s = 1.0 / (double)cfg.sample_rate_hz;
    long played_total = 0;
    while (!stop_flag) {
        if (restart_flag) {
            restart_flag = 0;
            if (configure() != 0) { /* a board reset: outputs safe, the index from its start, a DESCRIPTOR first */
                return 1;
            }
            logj("restarted", "");
        }
        if (started) {
            struct timespec now;
            clock_gettime(CLOCK_MONOTONIC, &now);
            double el = (double)(now.tv_sec - t0.tv_sec) + (double)(now.tv_nsec - t0.tv_nsec) * 1e-9;
            uint64_t due = (uint64_t)(el / period_s);
            while (ticks < due) {
                ms_tick(&dev);
                ticks++;
                played_total++;
                if (opt_once && played_total >= cap_n - opt_skip) {
                    stop_flag = 1;
                    break;
                }
            }
        }
        ms_poll(&dev);
        if (opt_modbus_tcp) {
            serve_modbus();
        } else if (opt_modbus_rtu) {
            serve_modbus_rtu();
        }
        ms_counters moved = dev.n;
        moved.frames_sent = logged_counters.frames_sent; /* a change of what is counted, not of the traffic */
        if (memcmp(&logged_counters, &moved, sizeof moved) != 0 && mono_s() - counters_logged_at >= 0.1) {
            log_counters("counters");
        }
        /* sleep until the next tick, or a byte from the host, or a client */
        struct pollfd fds[3];
        int nf = 0;
        if (listen_fd >= 0) { fds[nf].fd = listen_fd; fds[nf++].events = POLLIN; }
        if (client_fd >= 0) { fds[nf].fd = client_fd; fds[nf++].events = POLLIN; }
        if (pty_master >= 0) { fds[nf].fd = pty_master; fds[nf++].events = POLLIN; }
        struct timespec wait = {0, 1000000};
        if (started) {
            struct timespec now;
            clock_gettime(CLOCK_MONOTONIC, &now);
            double el = (double)(now.tv_sec - t0.tv_sec) + (double)(now.tv_nsec - t0.tv_nsec) * 1e-9;
            double next = (double)(ticks + 1) * period_s - el;
            if (next < 0) next = 0;
            wait.tv_sec = 0;
            wait.tv_nsec = (long)(next * 1e9);
            if (wait.tv_nsec > 999999999L) wait.tv_nsec = 999999999L;
        }
        int r = ppoll(fds, (nfds_t)nf, &wait, NULL);
        if (r > 0) {
            for (int k = 0; k < nf; k++) {
                if (fds[k].fd == listen_fd && (fds[k].revents & POLLIN)) {
                    accept_client();
                }
            }
        }
    }
    ms_poll(&dev);
    log_counters("stop");
    close_client("stop");
    if (opt_pty || opt_modbus_rtu) {
        unlink(opt_pty ? opt_pty : opt_modbus_rtu);
    }
    free(cap_samples);
    free(cap_ctxs);
    if (logf) fclose(logf);
    return 0;
}
