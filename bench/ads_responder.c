/*
 * A minimal, fast ADS server over AMS/TCP for the ADS benchmark, so that the figures
 * measure the clients rather than the server: both clients (pyads' AdsLib and
 * cellrt's) talk to it on 127.0.0.1 in the same run.
 *
 *   ads_responder [PORT]     listens on 127.0.0.1 (PORT 0 or none: the OS picks);
 *                            prints "port N" once listening; stops when stdin closes
 *
 * It serves 201 DINT symbols in index group 0x4040: "MAIN.counter" (42) and
 * "GVL.Io.P000" ... "GVL.Io.P199" (their number), names case-insensitive, and the
 * requests a client needs to read them: device info, state, symbol info by name
 * (0xF009), handles (0xF003, 0xF006), reads and writes by handle (0xF005) or by
 * index group and offset, the symbol version (0xF008), and sum reads, writes and
 * read-writes (0xF080, 0xF081, 0xF082). Anything else is "service not supported".
 * One thread, poll(2), every answer of a batch of requests in one write(2).
 */
#include <arpa/inet.h>
#include <ctype.h>
#include <errno.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <sys/socket.h>
#include <unistd.h>

#define NSYM 201
#define MAX_CLIENTS 16
#define IG_PLC_DATA 0x4040u
#define ERR_SERVICE 0x701u
#define ERR_GROUP 0x702u
#define ERR_OFFSET 0x703u
#define ERR_SIZE 0x705u
#define ERR_SYMBOL 0x710u

struct buf {
    unsigned char *p;
    size_t len, cap;
};

struct client {
    int fd;
    struct buf in, out;
};

static char names[NSYM][32];
static int32_t values[NSYM];

static void reserve(struct buf *b, size_t more) {
    if (b->len + more <= b->cap) return;
    size_t cap = b->cap ? b->cap : 4096;
    while (cap < b->len + more) cap *= 2;
    b->p = realloc(b->p, cap);
    if (!b->p) { perror("realloc"); exit(1); }
    b->cap = cap;
}

static void put(struct buf *b, const void *data, size_t n) {
    reserve(b, n);
    memcpy(b->p + b->len, data, n);
    b->len += n;
}

static void put32(struct buf *b, uint32_t v) {
    unsigned char x[4] = {v, v >> 8, v >> 16, v >> 24};
    put(b, x, 4);
}

static void put16(struct buf *b, uint16_t v) {
    unsigned char x[2] = {v, v >> 8};
    put(b, x, 2);
}

static uint32_t get32(const unsigned char *p) {
    return p[0] | p[1] << 8 | p[2] << 16 | (uint32_t)p[3] << 24;
}

static void set32(unsigned char *p, uint32_t v) {
    p[0] = v; p[1] = v >> 8; p[2] = v >> 16; p[3] = v >> 24;
}

/* The symbol a name stands for, or -1. */
static int lookup(const unsigned char *name, size_t n) {
    size_t len = strnlen((const char *)name, n);
    for (int i = 0; i < NSYM; i++)
        if (strlen(names[i]) == len && strncasecmp(names[i], (const char *)name, len) == 0)
            return i;
    return -1;
}

/* The symbol at an index group and offset (a handle is the symbol's number + 1). */
static int target(uint32_t group, uint32_t offset, uint32_t *err) {
    if (group == 0xF005u) {
        if (offset >= 1 && offset <= NSYM) return offset - 1;
        *err = ERR_SYMBOL;
        return -1;
    }
    if (group == IG_PLC_DATA) {
        if (offset % 4 == 0 && offset / 4 < NSYM) return offset / 4;
        *err = ERR_OFFSET;
        return -1;
    }
    *err = ERR_GROUP;
    return -1;
}

/* A read: its error code; the data (length bytes on success) appended to out. */
static uint32_t do_read(uint32_t group, uint32_t offset, uint32_t length, struct buf *out) {
    uint32_t err = 0;
    if (group == 0xF008u) {
        unsigned char v = 1;
        if (length < 1) return ERR_SIZE;
        put(out, &v, 1);
        return 0;
    }
    int s = target(group, offset, &err);
    if (s < 0) return err;
    if (length < 4) return ERR_SIZE;
    put32(out, (uint32_t)values[s]);
    return 0;
}

static uint32_t do_write(uint32_t group, uint32_t offset, const unsigned char *data,
                         uint32_t length) {
    uint32_t err = 0;
    if (group == 0xF006u) return length == 4 && get32(data) >= 1 && get32(data) <= NSYM
                                     ? 0 : ERR_SYMBOL;
    int s = target(group, offset, &err);
    if (s < 0) return err;
    if (length != 4) return ERR_SIZE;
    values[s] = (int32_t)get32(data);
    return 0;
}

/* A symbol entry as TwinCAT answers 0xF009. */
static void symbol_entry(int s, struct buf *out) {
    static const char type[] = "DINT";
    size_t nlen = strlen(names[s]);
    uint32_t length = 30 + nlen + 1 + sizeof type + 1;
    put32(out, length);
    put32(out, IG_PLC_DATA);
    put32(out, 4u * s);
    put32(out, 4);          /* size */
    put32(out, 3);          /* ADST_INT32 */
    put32(out, 0);          /* flags */
    put16(out, nlen);
    put16(out, sizeof type - 1);
    put16(out, 0);          /* comment */
    put(out, names[s], nlen + 1);
    put(out, type, sizeof type);
    put(out, "", 1);
}

static uint32_t do_read_write(uint32_t group, uint32_t offset, uint32_t rlen,
                              const unsigned char *w, uint32_t wlen, struct buf *out);

/* Sum commands: `n' sub-commands in `w'. */
static uint32_t do_sum(uint32_t group, uint32_t n, uint32_t rlen, const unsigned char *w,
                       uint32_t wlen, struct buf *out) {
    struct buf heads = {0}, datas = {0};
    uint32_t err = 0;
    size_t start = out->len;
    if (group == 0xF080u) {
        if ((uint64_t)n * 12 > wlen) return ERR_SIZE;
        for (uint32_t i = 0; i < n; i++) {
            const unsigned char *it = w + 12 * i;
            uint32_t len = get32(it + 8);
            size_t before = datas.len;
            uint32_t e = do_read(get32(it), get32(it + 4), len, &datas);
            put32(&heads, e);
            reserve(&datas, len);               /* a failed read's data: zeros */
            memset(datas.p + datas.len, 0, before + len - datas.len);
            datas.len = before + len;
        }
    } else if (group == 0xF081u) {
        if ((uint64_t)n * 12 > wlen) return ERR_SIZE;
        size_t pos = 12 * (size_t)n;
        for (uint32_t i = 0; i < n; i++) {
            const unsigned char *it = w + 12 * i;
            uint32_t len = get32(it + 8);
            if (pos + len > wlen) { err = ERR_SIZE; break; }
            put32(&heads, do_write(get32(it), get32(it + 4), w + pos, len));
            pos += len;
        }
    } else {
        if ((uint64_t)n * 16 > wlen) return ERR_SIZE;
        size_t pos = 16 * (size_t)n;
        for (uint32_t i = 0; i < n; i++) {
            const unsigned char *it = w + 16 * i;
            uint32_t wl = get32(it + 12);
            if (pos + wl > wlen) { err = ERR_SIZE; break; }
            size_t before = datas.len;
            uint32_t e = do_read_write(get32(it), get32(it + 4), get32(it + 8), w + pos, wl,
                                       &datas);
            put32(&heads, e);
            put32(&heads, datas.len - before);
            pos += wl;
        }
    }
    if (!err && heads.len + datas.len > rlen) err = ERR_SIZE;
    if (!err) {
        put(out, heads.p, heads.len);
        if (datas.len) put(out, datas.p, datas.len);
    } else {
        out->len = start;
    }
    free(heads.p);
    free(datas.p);
    return err;
}

static uint32_t do_read_write(uint32_t group, uint32_t offset, uint32_t rlen,
                              const unsigned char *w, uint32_t wlen, struct buf *out) {
    if (group == 0xF003u || group == 0xF009u) {
        int s = lookup(w, wlen);
        if (s < 0) return ERR_SYMBOL;
        if (group == 0xF003u) {
            if (rlen < 4) return ERR_SIZE;
            put32(out, s + 1);
        } else {
            symbol_entry(s, out);
        }
        return 0;
    }
    if (group == 0xF080u || group == 0xF081u || group == 0xF082u)
        return do_sum(group, offset, rlen, w, wlen, out);
    return ERR_GROUP;
}

/* Answers one AMS frame (header at `h', data after it) into `out'. */
static void answer(const unsigned char *h, struct buf *out) {
    const unsigned char *d = h + 32;
    uint16_t cmd = h[16] | h[17] << 8;
    uint32_t dlen = get32(h + 20);
    struct buf body = {0};
    uint32_t err = 0;

    switch (cmd) {
    case 1: { /* device info */
        unsigned char info[20] = {0};
        info[0] = 3; info[1] = 1; info[2] = 4024 & 0xFF; info[3] = 4024 >> 8;
        memcpy(info + 4, "Responder", 9);
        put32(&body, 0);
        put(&body, info, sizeof info);
        break;
    }
    case 4: /* state */
        put32(&body, 0);
        put16(&body, 5);
        put16(&body, 0);
        break;
    case 2: { /* read */
        if (dlen < 12) { put32(&body, ERR_SIZE); put32(&body, 0); break; }
        struct buf data = {0};
        err = do_read(get32(d), get32(d + 4), get32(d + 8), &data);
        put32(&body, err);
        put32(&body, err ? 0 : data.len);
        if (!err) put(&body, data.p, data.len);
        free(data.p);
        break;
    }
    case 3: /* write */
        if (dlen < 12 || get32(d + 8) > dlen - 12) { put32(&body, ERR_SIZE); break; }
        put32(&body, do_write(get32(d), get32(d + 4), d + 12, get32(d + 8)));
        break;
    case 9: { /* read-write */
        if (dlen < 16 || get32(d + 12) > dlen - 16) {
            put32(&body, ERR_SIZE); put32(&body, 0); break;
        }
        struct buf data = {0};
        err = do_read_write(get32(d), get32(d + 4), get32(d + 8), d + 16, get32(d + 12),
                            &data);
        put32(&body, err);
        put32(&body, err ? 0 : data.len);
        if (!err && data.len) put(&body, data.p, data.len);
        free(data.p);
        break;
    }
    default: /* notifications and the rest */
        put32(&body, ERR_SERVICE);
        if (cmd == 6) put32(&body, 0);
        break;
    }

    unsigned char hdr[38];
    hdr[0] = hdr[1] = 0;
    set32(hdr + 2, 32 + body.len);
    memcpy(hdr + 6, h + 8, 8);       /* to: who asked */
    memcpy(hdr + 14, h, 8);          /* from: whom it asked */
    hdr[22] = h[16]; hdr[23] = h[17];
    hdr[24] = 5; hdr[25] = 0;        /* a response over TCP */
    set32(hdr + 26, body.len);
    set32(hdr + 30, 0);
    memcpy(hdr + 34, h + 28, 4);     /* invoke id */
    put(out, hdr, sizeof hdr);
    if (body.len) put(out, body.p, body.len);
    free(body.p);
}

/* Answers every complete frame in the client's buffer; false on a malformed one. */
static int serve(struct client *c) {
    size_t pos = 0;
    while (c->in.len - pos >= 6) {
        const unsigned char *f = c->in.p + pos;
        uint32_t len = get32(f + 2);
        if (f[0] || f[1] || len < 32 || len > (1u << 24)) return 0;
        if (c->in.len - pos < 6 + len) break;
        if (get32(f + 6 + 20) <= len - 32 && !(f[6 + 18] & 1)) answer(f + 6, &c->out);
        pos += 6 + len;
    }
    memmove(c->in.p, c->in.p + pos, c->in.len - pos);
    c->in.len -= pos;
    return 1;
}

/* Writes what is pending; false when the client is gone. */
static int flush(struct client *c) {
    size_t done = 0;
    while (done < c->out.len) {
        ssize_t n = write(c->fd, c->out.p + done, c->out.len - done);
        if (n < 0) {
            if (errno == EAGAIN || errno == EWOULDBLOCK) break;
            if (errno == EINTR) continue;
            return 0;
        }
        done += n;
    }
    memmove(c->out.p, c->out.p + done, c->out.len - done);
    c->out.len -= done;
    return 1;
}

int main(int argc, char **argv) {
    strcpy(names[0], "MAIN.counter");
    values[0] = 42;
    for (int i = 1; i < NSYM; i++) {
        snprintf(names[i], sizeof names[i], "GVL.Io.P%03d", i - 1);
        values[i] = i - 1;
    }

    int lfd = socket(AF_INET, SOCK_STREAM, 0);
    int one = 1;
    setsockopt(lfd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    struct sockaddr_in a = {0};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    a.sin_port = htons(argc > 1 ? atoi(argv[1]) : 0);
    if (bind(lfd, (struct sockaddr *)&a, sizeof a) || listen(lfd, 16)) {
        perror("listen");
        return 1;
    }
    socklen_t alen = sizeof a;
    getsockname(lfd, (struct sockaddr *)&a, &alen);
    printf("port %d\n", ntohs(a.sin_port));
    fflush(stdout);

    struct client clients[MAX_CLIENTS];
    int n = 0;
    for (;;) {
        struct pollfd fds[MAX_CLIENTS + 2];
        fds[0] = (struct pollfd){.fd = 0, .events = POLLIN};
        fds[1] = (struct pollfd){.fd = lfd, .events = POLLIN};
        for (int i = 0; i < n; i++)
            fds[i + 2] = (struct pollfd){.fd = clients[i].fd,
                                         .events = POLLIN | (clients[i].out.len ? POLLOUT : 0)};
        if (poll(fds, n + 2, -1) < 0) {
            if (errno == EINTR) continue;
            perror("poll");
            return 1;
        }
        if (fds[0].revents) {
            char b[256];
            if (read(0, b, sizeof b) <= 0) return 0;   /* stdin closed: done */
        }
        if ((fds[1].revents & POLLIN) && n < MAX_CLIENTS) {
            int fd = accept(lfd, NULL, NULL);
            if (fd >= 0) {
                setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
                fcntl(fd, F_SETFL, fcntl(fd, F_GETFL) | O_NONBLOCK);
                clients[n++] = (struct client){.fd = fd};
            }
        }
        for (int i = n - 1; i >= 0; i--) {
            struct client *c = &clients[i];
            short ev = fds[i + 2].revents;
            int alive = 1;
            if (ev & (POLLIN | POLLHUP | POLLERR)) {
                reserve(&c->in, 65536);
                ssize_t got = read(c->fd, c->in.p + c->in.len, c->in.cap - c->in.len);
                if (got > 0) {
                    c->in.len += got;
                    alive = serve(c);
                } else if (got == 0 || (errno != EAGAIN && errno != EINTR)) {
                    alive = 0;
                }
            }
            if (alive && c->out.len) alive = flush(c);
            if (!alive) {
                close(c->fd);
                free(c->in.p);
                free(c->out.p);
                clients[i] = clients[--n];
            }
        }
    }
}
