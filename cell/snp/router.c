/* The two routers of cell.snp.routed in C: each router port a UDP socket joined to one node's socket
 * (its link), each datagram routed by its leading path address (cell.snp.spacewire.Router's path
 * addressing: the byte deleted, the rest sent out of that port), as a SpaceWire router forwards at
 * line rate where a Python loop added tens of microseconds a hop; each configuration port answers
 * an RMAP read of its router's identity (spacewire.Router.configure).  cell/snp/native.py's
 * RoutersState mirrors routers_t; a test holds it to spacewire.Router, datagram by datagram. */
#include "wire.h"

enum { ROUTER_PORTS = 31, ROUTERS = 2, IDENTITY_LEN = 8 };

typedef struct {
    int64_t n_ports;                               /* ports 1..n_ports on each router */
    int64_t fd[ROUTERS][ROUTER_PORTS];             /* port p's socket: [r][p - 1] */
    int64_t peer_ip[ROUTER_PORTS], peer_port[ROUTER_PORTS]; /* port p's node (the same on both) */
    int64_t up[ROUTERS][ROUTER_PORTS];
    /* counted per router: spacewire.RouterCounters' names */
    int64_t forwarded[ROUTERS], config[ROUTERS], bad_port[ROUTERS], link_down[ROUTERS], no_route[ROUTERS],
        bad_config[ROUTERS];
    int64_t dropped; /* from outside a link, or in at a link that is down */
} routers_t;

int snp_routers_size(void) {
    crc_init();
    return (int)sizeof(routers_t);
}

/* What reached router k's configuration port (p: after its 0 byte), in by port `in`: an RMAP read of
 * its identity (address 0, IDENTITY_LEN bytes) answered out of `in`, the read's reply address (its
 * leading zeros dropped) leading on; anything else dropped, counted. */
static void configure(routers_t *r, int k, int in, const uint8_t *p, ssize_t n) {
    /* the read: target, protocol 1, instruction (command, read, reply: ..ll the reply address's
     * words), key, reply address, initiator, transaction id u16, extended address, address u32,
     * length u24, header CRC */
    int nr = n >= 3 ? 4 * (p[2] & 3) : 0, head = 4 + nr + 8 + 3;
    if (n != head + 1 || p[1] != 1 || (p[2] & 0xE8) != 0x48 || crc8(p, (size_t)head) != p[head]) {
        r->bad_config[k]++;
        return;
    }
    const uint8_t *tail = p + 4 + nr; /* initiator, tid, extended, address, length */
    uint32_t address = (uint32_t)tail[4] << 24 | (uint32_t)tail[5] << 16 | (uint32_t)tail[6] << 8 | tail[7];
    uint32_t length = (uint32_t)tail[8] << 16 | (uint32_t)tail[9] << 8 | tail[10];
    if (tail[3] != 0 || address != 0 || length != IDENTITY_LEN) {
        r->bad_config[k]++;
        return;
    }
    uint8_t out[12 + 12 + IDENTITY_LEN + 1];
    size_t m = 0;
    for (int i = 0; i < nr; i++)
        if (m || p[4 + i]) out[m++] = p[4 + i];
    uint8_t *reply = out + m; /* initiator, 1, instruction, status, target, tid, 0, length u24, CRC */
    const uint8_t head_bytes[11] = {tail[0], 1, 0x0C, 0, p[0], tail[1], tail[2], 0, 0, 0, IDENTITY_LEN};
    memcpy(reply, head_bytes, 11);
    reply[11] = crc8(reply, 11);
    uint8_t *id = reply + 12;
    uint32_t mask = 0;
    for (int q = 1; q <= r->n_ports; q++)
        if (r->up[k][q - 1]) mask |= 1u << q;
    const uint8_t ident[IDENTITY_LEN] = {'R', (uint8_t)(k + 1), (uint8_t)r->n_ports, (uint8_t)in,
                                         (uint8_t)(mask >> 24), (uint8_t)(mask >> 16), (uint8_t)(mask >> 8),
                                         (uint8_t)mask};
    memcpy(id, ident, IDENTITY_LEN);
    id[IDENTITY_LEN] = crc8(id, IDENTITY_LEN);
    r->config[k]++;
    int64_t sent = 0, lost = 0, errors = 0;
    uint64_t rng = 1;
    send_lossy((int)r->fd[k][in - 1], out, m + 12 + IDENTITY_LEN + 1, r->peer_ip[in - 1], r->peer_port[in - 1], 0.0,
               &rng, &sent, &lost, &errors);
}

/* One datagram in at router r's port `in`, from ip:port: forwarded, or dropped and counted. */
static void route_one(routers_t *r, int k, int in, const uint8_t *p, ssize_t n, int64_t ip, int64_t port) {
    if (ip != r->peer_ip[in - 1] || port != r->peer_port[in - 1] || !r->up[k][in - 1] || n < 1) {
        r->dropped++;
        return;
    }
    int out = p[0];
    if (out == 0) {
        configure(r, k, in, p + 1, n - 1);
        return;
    }
    if (out > 31) { /* logical addressing: these routers hold no table */
        r->no_route[k]++;
        return;
    }
    if (out > r->n_ports) {
        r->bad_port[k]++;
        return;
    }
    if (!r->up[k][out - 1]) {
        r->link_down[k]++;
        return;
    }
    int64_t sent = 0, lost = 0, errors = 0;
    uint64_t rng = 1;
    send_lossy((int)r->fd[k][out - 1], p + 1, (size_t)n - 1, r->peer_ip[out - 1], r->peer_port[out - 1], 0.0, &rng,
               &sent, &lost, &errors);
    r->forwarded[k] += sent;
}

/* Route until host time `until` (CLOCK_MONOTONIC ns) or until wake_fd (the caller's orders) is
 * readable: 0, or 1 for the orders, or -errno. */
int snp_routers_run(routers_t *r, int64_t until, int64_t wake_fd) {
    struct pollfd fds[ROUTERS * ROUTER_PORTS + 1];
    int n = 0;
    for (int k = 0; k < ROUTERS; k++)
        for (int p = 0; p < r->n_ports; p++) fds[n].fd = (int)r->fd[k][p], fds[n++].events = POLLIN;
    fds[n].fd = (int)wake_fd, fds[n].events = POLLIN;
    uint8_t buf[2048];
    for (;;) {
        int64_t now = host_now();
        if (now >= until) return 0;
        int64_t wait = until - now;
        struct timespec ts = {wait / 1000000000, wait % 1000000000};
        int ready = ppoll(fds, (nfds_t)n + 1, &ts, NULL);
        if (ready < 0 && errno != EINTR) return -errno;
        if (ready <= 0) continue;
        if (fds[n].revents & POLLIN) return 1;
        for (int i = 0; i < n; i++) {
            if (!(fds[i].revents & (POLLIN | POLLERR))) continue;
            int k = i / (int)r->n_ports, in = i % (int)r->n_ports + 1;
            int64_t ip, port, at;
            ssize_t got;
            while ((got = receive(fds[i].fd, buf, sizeof buf, 0, &ip, &port, &at)) >= 0)
                route_one(r, k, in, buf, got, ip, port);
        }
    }
}
