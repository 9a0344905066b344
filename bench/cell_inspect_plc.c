/*
 * The PLCs of the inspection benchmark: a Modbus TCP server on libmodbus holding the
 * I/O blocks of many PLCs in its holding registers (one block per base register),
 * serving many connections at once, and reporting every write it receives.
 *
 *   cell_inspect_plc [PORT]   listens on 127.0.0.1:PORT (0 or none: a free port),
 *                             prints "port N" once listening
 *
 * Commands on stdin, one a line: "set ADDR V..." (a PLC writes registers), answered
 * "ok". Every register write received over the network (function codes 6, 16, 22) is
 * reported on stdout once answered: "w ADDR V...", the registers' new values.
 */
#include <errno.h>
#include <modbus/modbus.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/select.h>
#include <sys/socket.h>
#include <unistd.h>

#define SIZE 60000

static modbus_mapping_t *map;

static void command(char *line) {
    char *word = strtok(line, " \t\r\n");
    if (word && !strcmp(word, "set")) {
        char *a = strtok(NULL, " \t\r\n");
        int addr = a ? atoi(a) : 0;
        for (char *v; (v = strtok(NULL, " \t\r\n")) && addr < SIZE; addr++)
            map->tab_registers[addr] = (uint16_t)atoi(v);
        printf("ok\n");
    } else if (word) {
        printf("error %s\n", word);
    }
    fflush(stdout);
}

/* What a write request changed, from its PDU (after the 7 bytes of the MBAP header). */
static void report(const uint8_t *q) {
    int fc = q[7], addr = (q[8] << 8) | q[9], n;
    switch (fc) {
    case 0x06: case 0x16: n = 1; break;
    case 0x10: n = (q[10] << 8) | q[11]; break;
    default: return;
    }
    if (addr + n > SIZE) return;
    printf("w %d", addr);
    for (int i = 0; i < n; i++) printf(" %d", map->tab_registers[addr + i]);
    printf("\n");
}

int main(int argc, char **argv) {
    int port = argc > 1 ? atoi(argv[1]) : 0;
    modbus_t *ctx = modbus_new_tcp("127.0.0.1", port);
    uint8_t query[MODBUS_TCP_MAX_ADU_LENGTH];
    map = modbus_mapping_new(0, 0, SIZE, 0);
    if (!ctx || !map) { fprintf(stderr, "cannot create the server\n"); return 1; }
    int listener = modbus_tcp_listen(ctx, 256);
    if (listener < 0) { fprintf(stderr, "listen: %s\n", modbus_strerror(errno)); return 1; }
    struct sockaddr_in sa;
    socklen_t len = sizeof sa;
    getsockname(listener, (struct sockaddr *)&sa, &len);
    printf("port %d\n", ntohs(sa.sin_port));
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
            if (r <= 0) return 0;                       /* the benchmark is done */
            used += (size_t)r;
            line[used] = 0;
            char *nl;
            while ((nl = strchr(line, '\n'))) {
                *nl = 0;
                size_t rest = used - (size_t)(nl + 1 - line);
                command(line);
                memmove(line, nl + 1, rest);
                used = rest;
                line[used] = 0;
            }
        }
        if (FD_ISSET(listener, &rd)) {
            int fd = accept(listener, NULL, NULL);
            if (fd >= 0) {
                int one = 1;
                setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
                FD_SET(fd, &clients);
                if (fd > fdmax) fdmax = fd;
            }
        }
        int wrote = 0;
        for (int fd = 1; fd <= fdmax; fd++) {
            if (fd == listener || !FD_ISSET(fd, &clients) || !FD_ISSET(fd, &rd)) continue;
            modbus_set_socket(ctx, fd);
            int rc = modbus_receive(ctx, query);
            if (rc == -1) {
                close(fd);
                FD_CLR(fd, &clients);
                continue;
            }
            if (rc > 0) {
                modbus_reply(ctx, query, rc, map);
                report(query);
                wrote = 1;
            }
        }
        if (wrote) fflush(stdout);
    }
}
