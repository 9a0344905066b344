/*
 * A Modbus TCP server on libmodbus, the test and benchmark peer of cell_hal_modbus.
 *
 *   modbus_server [PORT]      listens on 127.0.0.1:PORT (0 or none: a free port),
 *                             prints "port N" once listening
 *
 * It answers unit 1 (and 255, the "this device" unit of Modbus TCP) from a map of
 * 10000 coils, discrete inputs, holding and input registers; another unit gets
 * exception 11 (gateway target failed to respond), as a gateway would answer.
 * Commands on stdin, one a line, each answered "ok ..." on stdout:
 *
 *   set co|di|hr|ir ADDR V...  set values (bits 0/1, registers 0..65535)
 *   get co|di|hr|ir ADDR N     "ok V..."
 *   silent 1|0                 stop answering requests (they time out) / answer again
 *   reject FC                  answer function FC with exception 1 (illegal function)
 *   refuse co|di|hr|ir ADDR C  answer every request that touches ADDR of that table
 *                              with exception C (0: answer it again)
 *   fail_every N C             answer each request (its table and first address) with
 *                              exception C every Nth time it is asked (0: stop)
 *   count co|di|hr|ir ADDR     "ok N": how many requests touched ADDR of that table
 *   notify_after co|di|hr|ir ADDR N
 *                              "ok", then "reached" once N requests have touched it
 *   mangle KIND                answer the next request with a faulty frame:
 *                              tid (another transaction id), unit (another unit),
 *                              proto (protocol id 1), oversize (length field 300),
 *                              fc (another function code), count (wrong byte count)
 *   drop                       close every client connection
 */
#include <errno.h>
#include <modbus/modbus.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/select.h>
#include <sys/socket.h>
#include <unistd.h>

#define SIZE 10000

static modbus_mapping_t *map;
static int silent = 0;
static int rejected[256];
static char mangle[16] = "";
static uint8_t refused[4][SIZE];     /* exception code per table and address, 0 none */
static int fail_every = 0, fail_code = 0;
static unsigned asked[4][SIZE];       /* requests that touched each address */
/* Requests since fail_every, by table and first address: counted per request, not
   across them, so that a client that asks a refused request again one poll later is
   not refused at the same place of its cycle every time. */
static unsigned fail_seen[4][SIZE], fail_other;
static int notify_table = -1, notify_addr = 0;
static unsigned notify_count = 0;

static int table_index(const char *t) {
    return !strcmp(t, "co") ? 0 : !strcmp(t, "di") ? 1 : !strcmp(t, "hr") ? 2 : 3;
}

/* The exception code a refused address in the request's span asks for, or 0; counts
   the request for each address it touches. */
static int refusal(const uint8_t *q) {
    int fc = q[7], addr = q[8] << 8 | q[9], n = 1, table;
    switch (fc) {
    case 1: case 15: table = 0; break;
    case 2: table = 1; break;
    case 3: case 6: case 16: case 22: case 23: table = 2; break;
    case 4: table = 3; break;
    default: return 0;
    }
    if (fc <= 4 || fc == 15 || fc == 16 || fc == 23) n = q[10] << 8 | q[11];
    int code = 0;
    for (int a = addr; a < addr + n && a < SIZE; a++) {
        asked[table][a]++;
        if (refused[table][a] && !code) code = refused[table][a];
    }
    if (notify_table == table && notify_addr >= addr && notify_addr < addr + n
        && asked[table][notify_addr] >= notify_count) {
        notify_table = -1;
        printf("reached\n");
        fflush(stdout);
    }
    return code;
}

/* The counter of fail_every for a request: its table and first address. */
static unsigned *fail_counter(const uint8_t *q) {
    int fc = q[7], addr = q[8] << 8 | q[9], table;
    switch (fc) {
    case 1: case 5: case 15: table = 0; break;
    case 2: table = 1; break;
    case 3: case 6: case 16: case 22: case 23: table = 2; break;
    case 4: table = 3; break;
    default: return &fail_other;
    }
    return addr < SIZE ? &fail_seen[table][addr] : &fail_other;
}

static void reply(const char *fmt, const char *extra) {
    printf(fmt, extra);
    fflush(stdout);
}

static int table_size(const char *t) {
    return (!strcmp(t, "co") || !strcmp(t, "di") || !strcmp(t, "hr") || !strcmp(t, "ir")) ? SIZE : 0;
}

static void command(char *line, fd_set *clients, int *fdmax, int listener) {
    char *argv[SIZE / 4 + 8];
    int argc = 0;
    for (char *tok = strtok(line, " \t\r\n"); tok && argc < (int)(sizeof argv / sizeof *argv);
         tok = strtok(NULL, " \t\r\n"))
        argv[argc++] = tok;
    if (argc == 0) return;
    if (!strcmp(argv[0], "set") && argc >= 4 && table_size(argv[1])) {
        int addr = atoi(argv[2]);
        for (int i = 3; i < argc && addr + i - 3 < SIZE; i++) {
            int v = atoi(argv[i]), a = addr + i - 3;
            if (!strcmp(argv[1], "co")) map->tab_bits[a] = v ? 1 : 0;
            else if (!strcmp(argv[1], "di")) map->tab_input_bits[a] = v ? 1 : 0;
            else if (!strcmp(argv[1], "hr")) map->tab_registers[a] = (uint16_t)v;
            else map->tab_input_registers[a] = (uint16_t)v;
        }
        reply("ok%s\n", "");
    } else if (!strcmp(argv[0], "get") && argc == 4 && table_size(argv[1])) {
        int addr = atoi(argv[2]), n = atoi(argv[3]);
        printf("ok");
        for (int a = addr; a < addr + n && a < SIZE; a++) {
            int v;
            if (!strcmp(argv[1], "co")) v = map->tab_bits[a];
            else if (!strcmp(argv[1], "di")) v = map->tab_input_bits[a];
            else if (!strcmp(argv[1], "hr")) v = map->tab_registers[a];
            else v = map->tab_input_registers[a];
            printf(" %d", v);
        }
        reply("\n%s", "");
    } else if (!strcmp(argv[0], "silent") && argc == 2) {
        silent = atoi(argv[1]);
        reply("ok%s\n", "");
    } else if (!strcmp(argv[0], "reject") && argc == 2) {
        rejected[atoi(argv[1]) & 0xFF] = 1;
        reply("ok%s\n", "");
    } else if (!strcmp(argv[0], "refuse") && argc == 4 && table_size(argv[1])) {
        int addr = atoi(argv[2]);
        if (addr >= 0 && addr < SIZE) refused[table_index(argv[1])][addr] = (uint8_t)atoi(argv[3]);
        reply("ok%s\n", "");
    } else if (!strcmp(argv[0], "count") && argc == 3 && table_size(argv[1])) {
        int addr = atoi(argv[2]);
        printf("ok %u\n", addr >= 0 && addr < SIZE ? asked[table_index(argv[1])][addr] : 0);
        fflush(stdout);
    } else if (!strcmp(argv[0], "notify_after") && argc == 4 && table_size(argv[1])) {
        notify_table = table_index(argv[1]);
        notify_addr = atoi(argv[2]);
        notify_count = (unsigned)atoi(argv[3]);
        reply("ok%s\n", "");
    } else if (!strcmp(argv[0], "fail_every") && argc == 3) {
        fail_every = atoi(argv[1]);
        fail_code = atoi(argv[2]);
        memset(fail_seen, 0, sizeof fail_seen);
        fail_other = 0;
        reply("ok%s\n", "");
    } else if (!strcmp(argv[0], "mangle") && argc == 2) {
        snprintf(mangle, sizeof mangle, "%s", argv[1]);
        reply("ok%s\n", "");
    } else if (!strcmp(argv[0], "drop")) {
        for (int fd = 0; fd <= *fdmax; fd++)
            if (FD_ISSET(fd, clients) && fd != listener && fd != 0) {
                close(fd);
                FD_CLR(fd, clients);
            }
        reply("ok%s\n", "");
    } else {
        reply("error %s\n", argv[0]);
    }
}

/* A faulty answer to the request in q (an MBAP header and a PDU). */
static void send_mangled(int fd, const uint8_t *q) {
    uint8_t b[400];
    int n = 0;
    memset(b, 0, sizeof b);
    b[0] = q[0]; b[1] = q[1];            /* transaction id */
    b[6] = q[6];                          /* unit */
    if (!strcmp(mangle, "oversize")) {
        b[4] = 300 >> 8; b[5] = 300 & 0xFF;
        n = 6 + 300;
    } else {
        /* a register read answer of one register by default */
        b[5] = 5; b[7] = q[7]; b[8] = 2; b[9] = 0; b[10] = 42;
        n = 11;
        if (!strcmp(mangle, "tid")) b[1] ^= 0x55;
        else if (!strcmp(mangle, "unit")) b[6] ^= 0x20;
        else if (!strcmp(mangle, "proto")) b[3] = 1;
        else if (!strcmp(mangle, "fc")) b[7] = q[7] == 4 ? 3 : 4;
        else if (!strcmp(mangle, "count")) b[8] = 7;
    }
    mangle[0] = 0;
    if (write(fd, b, n) < 0) perror("write");
}

int main(int argc, char **argv) {
    int port = argc > 1 ? atoi(argv[1]) : 0;
    modbus_t *ctx = modbus_new_tcp("127.0.0.1", port);
    uint8_t query[MODBUS_TCP_MAX_ADU_LENGTH];
    map = modbus_mapping_new(SIZE, SIZE, SIZE, SIZE);
    if (!ctx || !map) { fprintf(stderr, "cannot create the server\n"); return 1; }
    int listener = modbus_tcp_listen(ctx, 16);
    if (listener < 0) { fprintf(stderr, "listen: %s\n", modbus_strerror(errno)); return 1; }
    struct sockaddr_in addr;
    socklen_t len = sizeof addr;
    getsockname(listener, (struct sockaddr *)&addr, &len);
    printf("port %d\n", ntohs(addr.sin_port));
    fflush(stdout);

    fd_set clients;
    FD_ZERO(&clients);
    int fdmax = listener;
    char line[65536];
    size_t used = 0;
    for (;;) {
        fd_set rd = clients;
        FD_SET(0, &rd);
        FD_SET(listener, &rd);
        if (select(fdmax + 1, &rd, NULL, NULL, NULL) < 0) {
            if (errno == EINTR) continue;
            perror("select");
            return 1;
        }
        if (FD_ISSET(0, &rd)) {
            ssize_t r = read(0, line + used, sizeof line - 1 - used);
            if (r <= 0) return 0;                       /* the suite closed us */
            used += (size_t)r;
            line[used] = 0;
            char *nl;
            while ((nl = strchr(line, '\n'))) {
                *nl = 0;
                command(line, &clients, &fdmax, listener);
                size_t rest = used - (size_t)(nl + 1 - line);
                memmove(line, nl + 1, rest);
                used = rest;
                line[used] = 0;
            }
        }
        if (FD_ISSET(listener, &rd)) {
            int fd = accept(listener, NULL, NULL);
            if (fd >= 0) {
                /* Answers go out at once, even several in a row to pipelined requests. */
                int one = 1;
                setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
                FD_SET(fd, &clients);
                if (fd > fdmax) fdmax = fd;
            }
        }
        for (int fd = 1; fd <= fdmax; fd++) {
            if (fd == listener || !FD_ISSET(fd, &clients) || !FD_ISSET(fd, &rd)) continue;
            modbus_set_socket(ctx, fd);
            /* Every request already received is answered before waiting again, so
               pipelined requests cost one select, not one each. */
            int pending;
            do {
                int rc = modbus_receive(ctx, query);
                if (rc == -1) {
                    close(fd);
                    FD_CLR(fd, &clients);
                    break;
                }
                if (rc > 0 && !silent) {
                    int unit = query[6], fc = query[7], refuse = refusal(query);
                    int nth = fail_every > 0 && ++*fail_counter(query) % fail_every == 0;
                    if (mangle[0]) send_mangled(fd, query);
                    else if (nth)
                        modbus_reply_exception(ctx, query, fail_code);
                    else if (refuse)
                        modbus_reply_exception(ctx, query, refuse);
                    else if (unit != 1 && unit != 255)
                        modbus_reply_exception(ctx, query, MODBUS_EXCEPTION_GATEWAY_TARGET);
                    else if (rejected[fc])
                        modbus_reply_exception(ctx, query, MODBUS_EXCEPTION_ILLEGAL_FUNCTION);
                    else
                        modbus_reply(ctx, query, rc, map);
                }
                pending = 0;
                if (ioctl(fd, FIONREAD, &pending) < 0) pending = 0;
            } while (pending >= 7);   /* at least an MBAP header */
        }
    }
}
