/* The system calls of a durable file replacement and deletion, each made in one call
 * on a dirty I/O scheduler.
 *
 * Erlang's file module cannot open a directory, so it cannot fsync one: without that
 * a rename is not durable, and after a power cut the new name may be gone while a
 * later write (the sender forgetting its copy of a product) survived. And each of its
 * raw operations is a hand-off to a dirty scheduler of its own: open, write, flush,
 * close, rename and the folder's flush are six. Here they are one, which is what
 * makes a product transfer cost a few microseconds on a RAM disk rather than a few
 * hundred.
 *
 * Each runs on a dirty I/O scheduler, because on a disk a flush blocks for as long as
 * the disk takes, except in a folder held in RAM (tmpfs, ramfs), where nothing waits
 * for a device and the hand-off to another thread would cost more than the work: there
 * the same calls run on the calling scheduler, in microseconds.
 *
 * A process killed during a call on a dirty scheduler is gone at once, but the call
 * runs on to its end. So every replacement and deletion is entered, while it runs, in
 * a table of files being written, and a reader first waits until its file is not in
 * it: a task restarted after a crash reads what its last incarnation wrote, not the
 * file as it was a moment before that write landed. */
#include <erl_nif.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/uio.h>
#include <string.h>
#include <unistd.h>
#ifdef __linux__
#include <sys/vfs.h>
#define TMPFS_MAGIC_ 0x01021994UL
#define RAMFS_MAGIC_ 0x858458f6UL
#endif

/* The files being written: a slot per write under way. There are never more writes
 * under way than scheduler threads; a write finding the table full waits for a slot. */
#define IN_FLIGHT_MAX 256
static ErlNifMutex *flight_lock;
static ErlNifCond *flight_change;
static char *in_flight[IN_FLIGHT_MAX];

static int flying(const char *path)
{
    int i;

    for (i = 0; i < IN_FLIGHT_MAX; i++)
        if (in_flight[i] != NULL && strcmp(in_flight[i], path) == 0)
            return 1;
    return 0;
}

/* Enters a path in the table; the slot it took, or -1 without memory. */
static int flight_begin(const char *path)
{
    size_t len = strlen(path) + 1;
    char *copy = enif_alloc(len);
    int i;

    if (copy == NULL)
        return -1;
    memcpy(copy, path, len);
    enif_mutex_lock(flight_lock);
    for (;;) {
        for (i = 0; i < IN_FLIGHT_MAX; i++)
            if (in_flight[i] == NULL) {
                in_flight[i] = copy;
                enif_mutex_unlock(flight_lock);
                return i;
            }
        enif_cond_wait(flight_change, flight_lock);
    }
}

static void flight_end(int slot)
{
    char *copy;

    if (slot < 0)
        return;
    enif_mutex_lock(flight_lock);
    copy = in_flight[slot];
    in_flight[slot] = NULL;
    enif_cond_broadcast(flight_change);
    enif_mutex_unlock(flight_lock);
    enif_free(copy);
}

/* Errors named as Erlang's file module names them. */
static const char *errno_name(int err)
{
    switch (err) {
    case ENOENT: return "enoent";
    case ENOTDIR: return "enotdir";
    case EISDIR: return "eisdir";
    case EEXIST: return "eexist";
    case ENOTEMPTY: return "enotempty";
    case EXDEV: return "exdev";
    case EBUSY: return "ebusy";
    case EACCES: return "eacces";
    case EPERM: return "eperm";
    case EIO: return "eio";
    case EROFS: return "erofs";
    case ENOSPC: return "enospc";
    case EDQUOT: return "edquot";
    case EFBIG: return "efbig";
    case ELOOP: return "eloop";
    case ENAMETOOLONG: return "enametoolong";
    case EMFILE: return "emfile";
    case ENFILE: return "enfile";
    case ENOMEM: return "enomem";
    case EBADF: return "ebadf";
    case EINVAL: return "einval";
    default: return "eunknown";
    }
}

static ERL_NIF_TERM error2(ErlNifEnv *env, const char *where, int err)
{
    return enif_make_tuple2(env, enif_make_atom(env, "error"),
                            enif_make_tuple2(env, enif_make_atom(env, where),
                                             enif_make_atom(env, errno_name(err))));
}

/* A path argument as a NUL-terminated string; false if it is not one. */
static int get_path(ErlNifEnv *env, ERL_NIF_TERM term, char *buf, size_t size)
{
    ErlNifBinary bin;

    if (!enif_inspect_iolist_as_binary(env, term, &bin) || bin.size == 0 ||
        bin.size >= size || memchr(bin.data, 0, bin.size) != NULL)
        return 0;
    memcpy(buf, bin.data, bin.size);
    buf[bin.size] = '\0';
    return 1;
}

static int get_bool(ErlNifEnv *env, ERL_NIF_TERM term, int *value)
{
    char atom[6];

    if (!enif_get_atom(env, term, atom, sizeof atom, ERL_NIF_LATIN1))
        return 0;
    if (strcmp(atom, "true") == 0)
        *value = 1;
    else if (strcmp(atom, "false") == 0)
        *value = 0;
    else
        return 0;
    return 1;
}

/* fsync(2) of a folder; 0 or an errno. */
static int sync_dir(const char *dir)
{
    int fd, rc, err = 0;

    do { fd = open(dir, O_RDONLY | O_DIRECTORY | O_CLOEXEC); } while (fd < 0 && errno == EINTR);
    if (fd < 0)
        return errno;
    do { rc = fsync(fd); } while (rc < 0 && errno == EINTR);
    if (rc < 0)
        err = errno;
    close(fd);
    return err;
}

/* The folder a path is in: "." for a bare name, "/" for a name at the root. */
static void parent_of(const char *path, char *dir, size_t size)
{
    const char *slash = strrchr(path, '/');
    size_t len;

    if (slash == NULL) {
        strcpy(dir, ".");
        return;
    }
    len = slash == path ? 1 : (size_t)(slash - path);
    if (len >= size)
        len = size - 1;
    memcpy(dir, path, len);
    dir[len] = '\0';
}

static int pwrite_all(int fd, const unsigned char *data, size_t size, size_t offset)
{
    while (size > 0) {
        ssize_t n = pwrite(fd, data, size, (off_t)offset);
        if (n < 0) {
            if (errno == EINTR)
                continue;
            return errno;
        }
        data += n;
        offset += (size_t)n;
        size -= (size_t)n;
    }
    return 0;
}

static int write_all(int fd, const unsigned char *data, size_t size)
{
    while (size > 0) {
        ssize_t n = write(fd, data, size);
        if (n < 0) {
            if (errno == EINTR)
                continue;
            return errno;
        }
        data += n;
        size -= (size_t)n;
    }
    return 0;
}

static ERL_NIF_TERM fsync_dir(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char dir[PATH_MAX];
    int err;

    (void)argc;
    if (!get_path(env, argv[0], dir, sizeof dir))
        return enif_make_badarg(env);
    err = sync_dir(dir);
    if (err != 0)
        return enif_make_tuple2(env, enif_make_atom(env, "error"),
                                enif_make_atom(env, errno_name(err)));
    return enif_make_atom(env, "ok");
}

/* replace(Tmp, Path, Data, Sync): Data is written to Tmp, flushed (Sync), renamed over
 * Path, and Path's folder flushed (Sync). ok, or {error, {Where, Posix}} with Where
 * one of write, rename, dir; after an error Tmp is gone. */
static ERL_NIF_TERM replace_in(ErlNifEnv *env, const char *tmp, const char *path,
                               ErlNifBinary data, int sync);

static ERL_NIF_TERM replace(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char tmp[PATH_MAX], path[PATH_MAX];
    ErlNifBinary data;
    ERL_NIF_TERM result;
    int sync, slot;

    (void)argc;
    if (!get_path(env, argv[0], tmp, sizeof tmp) || !get_path(env, argv[1], path, sizeof path) ||
        !enif_inspect_iolist_as_binary(env, argv[2], &data) || !get_bool(env, argv[3], &sync))
        return enif_make_badarg(env);
    slot = flight_begin(path);
    result = replace_in(env, tmp, path, data, sync);
    flight_end(slot);
    return result;
}

static ERL_NIF_TERM replace_in(ErlNifEnv *env, const char *tmp, const char *path,
                               ErlNifBinary data, int sync)
{
    char dir[PATH_MAX];
    int fd, err = 0;

    do {
        fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    } while (fd < 0 && errno == EINTR);
    if (fd < 0)
        return error2(env, "write", errno);
    err = write_all(fd, data.data, data.size);
    if (err == 0 && sync && fdatasync(fd) < 0)
        err = errno;
    if (close(fd) < 0 && err == 0 && errno != EINTR)
        err = errno;
    if (err != 0) {
        unlink(tmp);
        return error2(env, "write", err);
    }
    if (rename(tmp, path) < 0) {
        err = errno;
        unlink(tmp);
        return error2(env, "rename", err);
    }
    if (sync) {
        parent_of(path, dir, sizeof dir);
        err = sync_dir(dir);
        if (err != 0)
            return error2(env, "dir", err);
    }
    return enif_make_atom(env, "ok");
}

/* remove(Path, Sync): Path is deleted (a missing one is no error) and its folder
 * flushed (Sync). ok, or {error, {Where, Posix}} with Where one of delete, dir. */
static ERL_NIF_TERM remove_in(ErlNifEnv *env, const char *path, int sync);

static ERL_NIF_TERM remove_file(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char path[PATH_MAX];
    ERL_NIF_TERM result;
    int sync, slot;

    (void)argc;
    if (!get_path(env, argv[0], path, sizeof path) || !get_bool(env, argv[1], &sync))
        return enif_make_badarg(env);
    slot = flight_begin(path);
    result = remove_in(env, path, sync);
    flight_end(slot);
    return result;
}

static ERL_NIF_TERM remove_in(ErlNifEnv *env, const char *path, int sync)
{
    char dir[PATH_MAX];
    int err;

    if (unlink(path) < 0) {
        if (errno == ENOENT)
            return enif_make_atom(env, "ok");
        return error2(env, "delete", errno);
    }
    if (sync) {
        parent_of(path, dir, sizeof dir);
        err = sync_dir(dir);
        if (err != 0)
            return error2(env, "dir", err);
    }
    return enif_make_atom(env, "ok");
}

/* -- Record files ----------------------------------------------------------------------
 *
 * A record file holds one term in two slots of equal size, each a header and a body:
 *
 *     "cellrt-record 1\n"  Seq:64  Len:32  CRC:32  Body:Len
 *
 * all big-endian, the CRC-32 (that of zlib and erlang:crc32/1) taken over Seq, Len and
 * Body. The valid slot with the higher Seq is the record. A write goes to the other
 * slot in place — one pwrite and one fdatasync, no new file, no rename, no folder to
 * flush — so a crash or a power cut during it leaves the record as it was, and the
 * torn slot fails its CRC. A file that does not exist yet, is not a record file, or
 * whose slots are too small for the record is written whole instead, as replace does,
 * with slots of room to grow. */

#define REC_MAGIC "cellrt-record 1\n"
#define REC_MAGIC_LEN 16
#define REC_HEADER 32
#define REC_MIN_SLOT 4096

static unsigned long crc_table[256];

static void crc_init(void)
{
    unsigned long c;
    int n, k;

    for (n = 0; n < 256; n++) {
        c = (unsigned long)n;
        for (k = 0; k < 8; k++)
            c = c & 1 ? 0xEDB88320UL ^ (c >> 1) : c >> 1;
        crc_table[n] = c;
    }
}

static unsigned long crc32_of(unsigned long crc, const unsigned char *p, size_t n)
{
    crc = crc ^ 0xFFFFFFFFUL;
    while (n-- > 0)
        crc = crc_table[(crc ^ *p++) & 0xFF] ^ (crc >> 8);
    return crc ^ 0xFFFFFFFFUL;
}

static void put_be(unsigned char *p, unsigned long long v, int bytes)
{
    int i;

    for (i = bytes - 1; i >= 0; i--) {
        p[i] = (unsigned char)(v & 0xFF);
        v >>= 8;
    }
}

static unsigned long long get_be(const unsigned char *p, int bytes)
{
    unsigned long long v = 0;
    int i;

    for (i = 0; i < bytes; i++)
        v = (v << 8) | p[i];
    return v;
}

/* The Seq of a valid slot, 0 for one that is not (Seq starts at 1). */
static unsigned long long slot_seq(const unsigned char *slot, size_t size)
{
    unsigned long long seq, len;

    if (size < REC_HEADER || memcmp(slot, REC_MAGIC, REC_MAGIC_LEN) != 0)
        return 0;
    seq = get_be(slot + 16, 8);
    len = get_be(slot + 24, 4);
    if (len > size - REC_HEADER)
        return 0;
    if (crc32_of(crc32_of(0, slot + 16, 12), slot + REC_HEADER, (size_t)len)
        != get_be(slot + 28, 4))
        return 0;
    return seq;
}

/* A slot's header for a body. */
static void slot_header(unsigned char *h, unsigned long long seq, const ErlNifBinary *body)
{
    memcpy(h, REC_MAGIC, REC_MAGIC_LEN);
    put_be(h + 16, seq, 8);
    put_be(h + 24, body->size, 4);
    put_be(h + 28, crc32_of(crc32_of(0, h + 16, 12), body->data, body->size), 4);
}

/* The name of the temporary file of a record written whole: "<Path>.tmp-<os pid>-<n>",
 * the name cell_file:cleanup/1 knows. False if it is too long. */
static int tmp_name(const char *path, char *tmp, size_t size)
{
    static unsigned long tmp_count;
    unsigned long n;

    enif_mutex_lock(flight_lock);
    n = ++tmp_count;
    enif_mutex_unlock(flight_lock);
    return snprintf(tmp, size, "%s.tmp-%ld-%lu", path, (long)getpid(), n) < (int)size;
}

/* The whole file for a first record or one that outgrew its slots: the record in the
 * first slot, the second empty; slots twice the record's size, in pages. */
static ERL_NIF_TERM record_fresh(ErlNifEnv *env, const char *path,
                                 const ErlNifBinary *body, unsigned long long seq, int sync)
{
    size_t slot = ((REC_HEADER + body->size) * 2 + REC_MIN_SLOT - 1) / REC_MIN_SLOT * REC_MIN_SLOT;
    char tmp[PATH_MAX];
    ErlNifBinary file;
    ERL_NIF_TERM result;

    if (!tmp_name(path, tmp, sizeof tmp))
        return enif_make_badarg(env);
    if (!enif_alloc_binary(slot * 2, &file))
        return error2(env, "write", ENOMEM);
    memset(file.data, 0, file.size);
    slot_header(file.data, seq, body);
    memcpy(file.data + REC_HEADER, body->data, body->size);
    result = replace_in(env, tmp, path, file, sync);
    enif_release_binary(&file);
    return result;
}

/* What a write needs to know of a record file: the size of its slots, the Seq of its
 * record and the slot holding it. */
typedef struct {
    size_t slot;
    unsigned long long seq;
    int cur;
} rec_state;

/* rec_state of an open file, read whole, and its stat (fs): 0, an errno, or REC_NOT_OURS
 * for a file that is not a record file or holds no whole record (it is written whole,
 * with a Seq above st->seq, 0 if it is not a record file at all). */
#define REC_NOT_OURS (-1)

static int rec_read_state(int fd, rec_state *st, struct stat *fs)
{
    unsigned char *file;
    unsigned long long seq_a, seq_b;
    size_t slot;
    ssize_t n;
    int err;

    st->seq = 0;
    if (fstat(fd, fs) < 0)
        return errno;
    slot = (size_t)fs->st_size / 2;
    if (fs->st_size % 2 != 0 || slot < REC_HEADER || slot > 64 * 1024 * 1024)
        return REC_NOT_OURS;
    file = enif_alloc((size_t)fs->st_size);
    if (file == NULL)
        return ENOMEM;
    do { n = pread(fd, file, (size_t)fs->st_size, 0); } while (n < 0 && errno == EINTR);
    if (n != fs->st_size) {
        err = n < 0 ? errno : EIO;
        enif_free(file);
        return err;
    }
    seq_a = slot_seq(file, slot);
    seq_b = slot_seq(file + slot, slot);
    enif_free(file);
    st->slot = slot;
    st->seq = seq_a > seq_b ? seq_a : seq_b;
    st->cur = seq_a >= seq_b ? 0 : 1;
    return st->seq == 0 ? REC_NOT_OURS : 0;
}

/* Writes a body as the next record of a file whose state is known, in the slot not
 * holding the record, and flushes it (sync): 0 or an errno. The state follows. */
static int rec_write_next(int fd, rec_state *st, const ErlNifBinary *body, int sync)
{
    unsigned char header[REC_HEADER];
    struct iovec iov[2];
    size_t target = st->cur == 0 ? st->slot : 0, total = REC_HEADER + body->size;
    ssize_t n;
    int err = 0;

    slot_header(header, st->seq + 1, body);
    iov[0].iov_base = header;
    iov[0].iov_len = REC_HEADER;
    iov[1].iov_base = body->data;
    iov[1].iov_len = body->size;
    do { n = pwritev(fd, iov, 2, (off_t)target); } while (n < 0 && errno == EINTR);
    if (n < 0)
        return errno;
    /* The rest of a short write: the header's, then the body's. */
    if ((size_t)n < REC_HEADER) {
        err = pwrite_all(fd, header + n, REC_HEADER - (size_t)n, target + (size_t)n);
        n = REC_HEADER;
    }
    if (err == 0 && (size_t)n < total)
        err = pwrite_all(fd, body->data + (n - REC_HEADER), total - (size_t)n, target + (size_t)n);
    if (err == 0 && sync && fdatasync(fd) < 0)
        err = errno;
    if (err == 0) {
        st->seq++;
        st->cur = target == 0 ? 0 : 1;
    }
    return err;
}

static ERL_NIF_TERM record_put_in(ErlNifEnv *env, const char *path,
                                  const ErlNifBinary *body, int sync)
{
    rec_state st;
    struct stat fs;
    int fd, err;

    do { fd = open(path, O_RDWR | O_CLOEXEC); } while (fd < 0 && errno == EINTR);
    if (fd < 0) {
        if (errno == ENOENT)
            return record_fresh(env, path, body, 1, sync);
        return error2(env, "write", errno);
    }
    err = rec_read_state(fd, &st, &fs);
    if (err == REC_NOT_OURS || (err == 0 && REC_HEADER + body->size > st.slot)) {
        close(fd);
        return record_fresh(env, path, body, st.seq + 1, sync);
    }
    if (err == 0)
        err = rec_write_next(fd, &st, body, sync);
    if (close(fd) < 0 && err == 0 && errno != EINTR)
        err = errno;
    if (err != 0)
        return error2(env, "write", err);
    return enif_make_atom(env, "ok");
}

/* record_put(Path, Body, Sync): Body becomes the record of Path. ok, or
 * {error, {Where, Posix}} with Where one of write, rename, dir. */
static ERL_NIF_TERM record_put(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char path[PATH_MAX];
    ErlNifBinary body;
    ERL_NIF_TERM result;
    int sync, slot;

    (void)argc;
    if (!get_path(env, argv[0], path, sizeof path) || !enif_inspect_iolist_as_binary(env, argv[1], &body) ||
        !get_bool(env, argv[2], &sync) || body.size > 0xFFFFFFFFUL)
        return enif_make_badarg(env);
    slot = flight_begin(path);
    result = record_put_in(env, path, &body, sync);
    flight_end(slot);
    return result;
}

/* -- Record files kept open ------------------------------------------------------------
 *
 * A task rewrites its product file at every step of a transfer. A handle on the file
 * keeps it open and remembers its state, so a write is a check that the file at the
 * path is still the one open (it may have been set aside, replaced or deleted
 * meanwhile: the handle then opens the file anew) and one pwritev, instead of an open,
 * a read of both slots and a close. Every write of the file must go through its
 * handle while the handle is used; a write by path is not seen by it.
 *
 * Few files are kept open at once (a quarter of the process's file limit, at most
 * 4096); past that a handle opens its file for each write as record_put does. */

typedef struct {
    ErlNifMutex *lock;
    char *path;
    int fd;
    int kept;              /* counted in kept_open */
    dev_t dev;
    ino_t ino;
    rec_state st;
} rec_handle;

static ErlNifResourceType *rec_handle_type;
static int kept_open, kept_max;

/* Closes the file, if open: the next write opens it anew. */
static void handle_forget(rec_handle *h)
{
    if (h->fd < 0)
        return;
    close(h->fd);
    h->fd = -1;
    if (h->kept) {
        enif_mutex_lock(flight_lock);
        kept_open--;
        enif_mutex_unlock(flight_lock);
        h->kept = 0;
    }
}

static void handle_dtor(ErlNifEnv *env, void *obj)
{
    rec_handle *h = obj;

    (void)env;
    handle_forget(h);
    if (h->lock != NULL)
        enif_mutex_destroy(h->lock);
    enif_free(h->path);
}

/* Opens the file and reads its state: 0, an errno, or REC_NOT_OURS (h->st.seq is then
 * the Seq to write above). */
static int handle_adopt(rec_handle *h)
{
    struct stat fs;
    int err;

    do { h->fd = open(h->path, O_RDWR | O_CLOEXEC); } while (h->fd < 0 && errno == EINTR);
    if (h->fd < 0) {
        h->st.seq = 0;
        return errno;
    }
    err = rec_read_state(h->fd, &h->st, &fs);
    if (err != 0) {
        close(h->fd);
        h->fd = -1;
        return err;
    }
    h->dev = fs.st_dev;
    h->ino = fs.st_ino;
    enif_mutex_lock(flight_lock);
    h->kept = kept_open < kept_max;
    kept_open += h->kept;
    enif_mutex_unlock(flight_lock);
    return 0;
}

static ERL_NIF_TERM handle_put_in(ErlNifEnv *env, rec_handle *h, const ErlNifBinary *body,
                                  int sync)
{
    struct stat fs;
    int err;

    if (h->fd >= 0 && (stat(h->path, &fs) < 0 || fs.st_dev != h->dev || fs.st_ino != h->ino
                       || (size_t)fs.st_size != 2 * h->st.slot))
        handle_forget(h);
    if (h->fd < 0) {
        err = handle_adopt(h);
        if (err != 0 && err != ENOENT && err != REC_NOT_OURS)
            return error2(env, "write", err);
        if (err != 0)
            return record_fresh(env, h->path, body, h->st.seq + 1, sync);
    }
    if (REC_HEADER + body->size > h->st.slot) {
        /* Outgrown: written whole with bigger slots, opened anew next time. */
        handle_forget(h);
        return record_fresh(env, h->path, body, h->st.seq + 1, sync);
    }
    err = rec_write_next(h->fd, &h->st, body, sync);
    if (err != 0 || !h->kept)
        handle_forget(h);
    if (err != 0)
        return error2(env, "write", err);
    return enif_make_atom(env, "ok");
}

/* record_open(Path): a handle on the record file Path (nothing is opened yet). */
static ERL_NIF_TERM record_open(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char path[PATH_MAX];
    rec_handle *h;
    ERL_NIF_TERM term;
    size_t len;

    (void)argc;
    if (!get_path(env, argv[0], path, sizeof path))
        return enif_make_badarg(env);
    h = enif_alloc_resource(rec_handle_type, sizeof *h);
    if (h == NULL)
        return enif_raise_exception(env, enif_make_atom(env, "enomem"));
    memset(h, 0, sizeof *h);
    h->fd = -1;
    len = strlen(path) + 1;
    h->path = enif_alloc(len);
    h->lock = enif_mutex_create("cell_file_record");
    if (h->path == NULL || h->lock == NULL) {
        enif_release_resource(h);
        return enif_raise_exception(env, enif_make_atom(env, "enomem"));
    }
    memcpy(h->path, path, len);
    term = enif_make_resource(env, h);
    enif_release_resource(h);
    return term;
}

/* record_put_handle(Handle, Body, Sync): as record_put, through a handle. */
static ERL_NIF_TERM record_put_handle(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    rec_handle *h;
    ErlNifBinary body;
    ERL_NIF_TERM result;
    int sync, slot;

    (void)argc;
    if (!enif_get_resource(env, argv[0], rec_handle_type, (void **)&h) ||
        !enif_inspect_iolist_as_binary(env, argv[1], &body) || !get_bool(env, argv[2], &sync) ||
        body.size > 0xFFFFFFFFUL)
        return enif_make_badarg(env);
    enif_mutex_lock(h->lock);
    slot = flight_begin(h->path);
    result = handle_put_in(env, h, &body, sync);
    flight_end(slot);
    enif_mutex_unlock(h->lock);
    return result;
}

/* -- Append files ---------------------------------------------------------------------
 *
 * A journal: data appended at the end of one file by its one writer, through a handle
 * that keeps it open, each append one write (and one fdatasync when asked). In a folder
 * held in RAM the append runs on the calling scheduler, as the other writes do. */

typedef struct {
    int fd;
} app_handle;

static ErlNifResourceType *app_handle_type;

static void app_dtor(ErlNifEnv *env, void *obj)
{
    app_handle *h = obj;

    (void)env;
    if (h->fd >= 0)
        close(h->fd);
}

/* append_open(Path): {ok, Handle} or {error, {open, Errno}}; the file is created if it
 * does not exist. */
static ERL_NIF_TERM append_open(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char path[PATH_MAX];
    app_handle *h;
    ERL_NIF_TERM term;
    int fd;

    (void)argc;
    if (!get_path(env, argv[0], path, sizeof path))
        return enif_make_badarg(env);
    do { fd = open(path, O_WRONLY | O_APPEND | O_CREAT | O_CLOEXEC, 0644); }
    while (fd < 0 && errno == EINTR);
    if (fd < 0)
        return error2(env, "open", errno);
    h = enif_alloc_resource(app_handle_type, sizeof *h);
    if (h == NULL) {
        close(fd);
        return enif_raise_exception(env, enif_make_atom(env, "enomem"));
    }
    h->fd = fd;
    term = enif_make_resource(env, h);
    enif_release_resource(h);
    return enif_make_tuple2(env, enif_make_atom(env, "ok"), term);
}

/* append(Handle, Data, Sync): ok, or {error, {write | sync, Errno}}. */
static ERL_NIF_TERM append(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    app_handle *h;
    ErlNifBinary data;
    int sync, err;

    (void)argc;
    if (!enif_get_resource(env, argv[0], app_handle_type, (void **)&h) ||
        !enif_inspect_iolist_as_binary(env, argv[1], &data) || !get_bool(env, argv[2], &sync))
        return enif_make_badarg(env);
    if (h->fd < 0)
        return error2(env, "write", EBADF);
    err = write_all(h->fd, data.data, data.size);
    if (err != 0)
        return error2(env, "write", err);
    if (sync && fdatasync(h->fd) < 0)
        return error2(env, "sync", errno);
    return enif_make_atom(env, "ok");
}

/* append_close(Handle): closes the file now (the handle is unusable after). */
static ERL_NIF_TERM append_close(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    app_handle *h;

    (void)argc;
    if (!enif_get_resource(env, argv[0], app_handle_type, (void **)&h))
        return enif_make_badarg(env);
    if (h->fd >= 0) {
        close(h->fd);
        h->fd = -1;
    }
    return enif_make_atom(env, "ok");
}

/* writing(Path): whether a replacement or deletion of Path is under way. */
static ERL_NIF_TERM writing(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char path[PATH_MAX];
    int busy;

    (void)argc;
    if (!get_path(env, argv[0], path, sizeof path))
        return enif_make_badarg(env);
    enif_mutex_lock(flight_lock);
    busy = flying(path);
    enif_mutex_unlock(flight_lock);
    return enif_make_atom(env, busy ? "true" : "false");
}

/* settle(Path): returns once no replacement or deletion of Path is under way. */
static ERL_NIF_TERM settle(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char path[PATH_MAX];

    (void)argc;
    if (!get_path(env, argv[0], path, sizeof path))
        return enif_make_badarg(env);
    enif_mutex_lock(flight_lock);
    while (flying(path))
        enif_cond_wait(flight_change, flight_lock);
    enif_mutex_unlock(flight_lock);
    return enif_make_atom(env, "ok");
}

/* in_ram(Dir): {ok, Bool}, whether a folder's file system is held in RAM. */
static ERL_NIF_TERM in_ram(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char dir[PATH_MAX];
    int ram = 0;

    (void)argc;
    if (!get_path(env, argv[0], dir, sizeof dir))
        return enif_make_badarg(env);
#ifdef __linux__
    {
        struct statfs fs;
        if (statfs(dir, &fs) < 0)
            return enif_make_tuple2(env, enif_make_atom(env, "error"),
                                    enif_make_atom(env, errno_name(errno)));
        ram = (unsigned long)fs.f_type == TMPFS_MAGIC_ || (unsigned long)fs.f_type == RAMFS_MAGIC_;
    }
#endif
    return enif_make_tuple2(env, enif_make_atom(env, "ok"),
                            enif_make_atom(env, ram ? "true" : "false"));
}

static ErlNifFunc funcs[] = {
    {"fsync_dir", 1, fsync_dir, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"replace_nif", 4, replace, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"remove_nif", 2, remove_file, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"replace_ram_nif", 4, replace, 0},
    {"remove_ram_nif", 2, remove_file, 0},
    {"in_ram_nif", 1, in_ram, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"record_put_nif", 3, record_put, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"record_put_ram_nif", 3, record_put, 0},
    {"record_open_nif", 1, record_open, 0},
    {"record_put_handle_nif", 3, record_put_handle, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"record_put_handle_ram_nif", 3, record_put_handle, 0},
    {"append_open_nif", 1, append_open, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"append_nif", 3, append, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"append_ram_nif", 3, append, 0},
    {"append_close_nif", 1, append_close, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"writing_nif", 1, writing, 0},
    {"settle_nif", 1, settle, ERL_NIF_DIRTY_JOB_IO_BOUND}
};

static int load(ErlNifEnv *env, void **priv_data, ERL_NIF_TERM load_info)
{
    struct rlimit lim;

    (void)priv_data;
    (void)load_info;
    crc_init();
    rec_handle_type = enif_open_resource_type(env, NULL, "cell_file_record", handle_dtor,
                                              ERL_NIF_RT_CREATE, NULL);
    kept_max = 16;
    if (getrlimit(RLIMIT_NOFILE, &lim) == 0)
        kept_max = lim.rlim_cur == RLIM_INFINITY || lim.rlim_cur / 4 > 4096
            ? 4096 : (int)(lim.rlim_cur / 4);
    app_handle_type = enif_open_resource_type(env, NULL, "cell_file_append", app_dtor,
                                              ERL_NIF_RT_CREATE, NULL);
    flight_lock = enif_mutex_create("cell_file_in_flight");
    flight_change = enif_cond_create("cell_file_in_flight");
    return rec_handle_type == NULL || app_handle_type == NULL || flight_lock == NULL ||
        flight_change == NULL;
}

ERL_NIF_INIT(cell_file, funcs, load, NULL, NULL, NULL)
