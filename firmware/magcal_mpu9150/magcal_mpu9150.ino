// magcal device firmware for an Arduino Uno (ATmega328P) wired to an MPU-9150, an MPU-9250/9255
// or an ICM-20948.
//
// Speaks docs/protocol.md v1 at 115200 baud: identity (which chip, and its magnetometer's
// resolution), single magnetometer measurements at a configurable rate (DRDY polled, ST2
// reported), streaming, a calibration record in EEPROM (version + CRC-16, never applied when
// blank or corrupt), calibrated output, and a standalone sphere fit that needs no host.
//
// Wiring: SDA A4, SCL A5, VCC 3.3 V (through a level shifter or a 3.3 V-tolerant breakout). AD0
// either way: the IMU is looked for at 0x68 (AD0 low), then 0x69 (AD0 high), at every bring-up,
// and recognised by its WHO_AM_I: 0x68 MPU-9150 (AK8975), 0x71/0x73 MPU-9250/9255 (AK8963),
// 0xEA ICM-20948 (AK09916; its WHO_AM_I is register 0x00 of bank 0). The magnetometer (0x0C) is
// reached through the IMU's I2C bypass, and its raw counts go on the wire; the host applies the
// sensitivity adjustment (ASA, in the hello) and the µT per count the hello's `bits` implies.
//
// The AK8963 is run at 16-bit output (0.15 µT per count); build with -DAK8963_BITS=14
// (`make -C firmware` builds that variant too) for 14-bit output (0.6 µT per count).
//
// Everything is float32 or integer: on the AVR `double` is 32-bit and `int` 16-bit.

#include <Arduino.h>
#include <EEPROM.h>
#include <Wire.h>
#include <avr/interrupt.h>
#include <avr/pgmspace.h>
#include <avr/sleep.h>

#include "sphere_fit.h"

#define FW_VERSION "0.3.0" // 0.2: the MPU-9250/9255 and ICM-20948; the hello states bits; 0.3: samples carry the accelerometer
#define PROTO_VERSION 1

#ifndef AK8963_BITS
#define AK8963_BITS 16
#endif
#if AK8963_BITS != 14 && AK8963_BITS != 16
#error "AK8963_BITS is 14 or 16"
#endif

// ---- chip facts ---------------------------------------------------------------------------
// IMUs: the MPU-6050/9150 and MPU-9250 register maps; the ICM-20948 datasheet (bank 0).
static const uint8_t MPU_ADDR_AD0_LOW = 0x68, MPU_ADDR_AD0_HIGH = 0x69;
static const uint8_t MPU_ACCEL_XOUT_H = 0x3B, ICM_ACCEL_XOUT_H = 0x2D; // X, Y, Z high then low, +-2 g
static const uint8_t MPU_INT_PIN_CFG = 0x37, MPU_TEMP_OUT_H = 0x41, MPU_USER_CTRL = 0x6A,
                     MPU_PWR_MGMT_1 = 0x6B, MPU_WHO_AM_I = 0x75;
static const uint8_t ICM_WHO_AM_I = 0x00, ICM_USER_CTRL = 0x03, ICM_PWR_MGMT_1 = 0x06,
                     ICM_INT_PIN_CFG = 0x0F, ICM_TEMP_OUT_H = 0x39, ICM_REG_BANK_SEL = 0x7F;
static const uint8_t WHO_MPU9150 = 0x68, WHO_MPU9250 = 0x71, WHO_MPU9255 = 0x73,
                     WHO_ICM20948 = 0xEA;
// Magnetometers at 0x0C: AK8975 (datasheet MS1187-E-02), AK8963 (MS1356-E-02), AK09916.
static const uint8_t AK_ADDR = 0x0C;
static const uint8_t AK_WIA = 0x00, AK09916_WIA2_VALUE = 0x09; // WIA2 is register 0x01
static const uint8_t AK_ST1 = 0x02, AK_HXL = 0x03, AK_ST2 = 0x09, AK_CNTL = 0x0A,
                     AK8963_CNTL2 = 0x0B, AK_ASTC = 0x0C, AK_ASAX = 0x10, ASTC_SELF = 0x40;
static const uint8_t AK09916_ST1 = 0x10, AK09916_HXL = 0x11, AK09916_ST2 = 0x18,
                     AK09916_CNTL2 = 0x31, AK09916_CNTL3 = 0x32;
static const uint8_t AK_SINGLE = 0x01, AK_SELF_TEST = 0x08, AK09916_SELF_TEST = 0x10,
                     AK_FUSE_ROM = 0x0F, AK_POWER_DOWN = 0x00, AK8963_BIT_16 = 0x10;
static const uint8_t ST2_DERR = 0x04, ST2_HOFL = 0x08;

enum Imu : uint8_t { IMU_NONE, IMU_MPU9150, IMU_MPU9250, IMU_ICM20948 };
enum Mag : uint8_t { MAG_NONE, MAG_AK8975, MAG_AK8963, MAG_AK09916 };
static const uint16_t DRDY_FIRST_POLL_US = 7000, DRDY_POLL_US = 500;
static const uint16_t DRDY_TIMEOUT_US = 30000;

// ---- protocol limits ----------------------------------------------------------------------
static const uint8_t MAX_LINE = 120;               // bytes including '$' and '\n'
static const uint8_t MAX_ARGS = 19;                // W carries 19
static const uint8_t RECORD_FIELDS = 18;
static const uint8_t EE_MAGIC = 0x4D;              // byte 0; record at 1..72, CRC at 73..74
static const uint8_t EE_SIZE = 1 + 4 * RECORD_FIELDS + 2;

enum RecordStatus : uint8_t { REC_OK, REC_BLANK, REC_CORRUPT };

// ---- state --------------------------------------------------------------------------------
static uint16_t g_seq;
static uint8_t g_who, g_wia, g_asa[3];
static uint8_t g_mpu = MPU_ADDR_AD0_LOW; // the IMU's address found at bring-up
static uint8_t g_imu, g_mag;            // which IMU and magnetometer (Imu, Mag)
static uint8_t g_bits;                  // the magnetometer's output resolution: 13, 14 or 16
static int16_t g_count_min, g_count_max; // the rails: a count there is no reading
static float g_ut_per_count;            // before ASA
static uint8_t g_rate_hz;
static bool g_streaming;
static uint8_t g_mode;                  // 0 raw S lines, 1 calibrated U lines
static int32_t g_rec[RECORD_FIELDS];    // the stored record (all 0 unless REC_OK)
static uint16_t g_rec_crc;
static uint8_t g_rec_status;

static bool g_measuring;                // a single measurement was triggered
static uint32_t g_trig_us, g_trig_ms, g_next_poll_us, g_sched_us;

static char g_fit_kind;                 // 0, 'F' (centred, stored) or 'N' (naive, reported)
static uint16_t g_fit_tag, g_fit_target, g_fit_count;
static SphereSums g_sums;

static char g_in[MAX_LINE];             // payload of the line being received (after '$')
static uint8_t g_in_len;
static bool g_in_active, g_in_long;

static char g_out[MAX_LINE];
static uint8_t g_out_len;

// ---- declarations (no IDE prototypes) -----------------------------------------------------
static uint8_t crc8_update(uint8_t crc, uint8_t b);
static uint16_t crc16_update(uint16_t crc, uint8_t b);
static uint16_t record_crc(const int32_t *v);
static void out_begin(char type);
static void out_char(char c);
static void out_int(int32_t v);
static void out_str_P(PGM_P s);
static void out_hex(uint16_t v, uint8_t digits);
static void out_end();
static bool i2c_write(uint8_t addr, uint8_t reg, uint8_t v);
static bool i2c_read(uint8_t addr, uint8_t reg, uint8_t *buf, uint8_t n);
static bool imu_find();
static void imu_bypass();
static void mag_find();
static void mag_setup();
static bool mag_mode(uint8_t mode);
static bool mag_ready();
static void mag_release();
static bool mag_read(int16_t h[3], uint8_t *st2);
static void bring_up();
static void send_hello();
static void send_ack(uint16_t tag, char cmd);
static void send_error_P(uint16_t tag, char cmd, PGM_P code);
static void send_record(uint16_t tag);
static void load_record();
static void store_record(const int32_t *v);
static void start_measurement(uint32_t now_us);
static void finish_measurement();
static void self_test(uint16_t tag);
static void poll_measurement();
static void emit_sample(const int16_t h[3], uint8_t st2, int16_t temp, const int16_t *accel);
static void fit_add(const int16_t h[3]);
static void fit_finish();
static float counts_to_ut(int16_t counts, uint8_t axis);
static void handle_line(char *line, uint8_t len);
static void handle_command(char cmd, uint16_t tag, const int32_t *args, uint8_t nargs,
                           const char *crc_tok);
static bool parse_int(const char *tok, int32_t *out);
static int32_t parse_hex(const char *tok, uint8_t digits);
static void poll_serial();
static void soft_reset();
static void idle();

// ---- checksums ------------------------------------------------------------------------------
static uint8_t crc8_update(uint8_t crc, uint8_t b)
{
    crc ^= b;
    for (uint8_t i = 0; i < 8; i++)
        crc = (crc & 0x80) ? (uint8_t)((crc << 1) ^ 0x07) : (uint8_t)(crc << 1);
    return crc;
}

static uint16_t crc16_update(uint16_t crc, uint8_t b)
{
    crc ^= (uint16_t)b << 8;
    for (uint8_t i = 0; i < 8; i++)
        crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
    return crc;
}

// CRC-16/CCITT-FALSE over the 18 values as little-endian int32 (docs/protocol.md).
static uint16_t record_crc(const int32_t *v)
{
    uint16_t crc = 0xFFFF;
    for (uint8_t i = 0; i < RECORD_FIELDS; i++) {
        uint32_t u = (uint32_t)v[i];
        for (uint8_t k = 0; k < 4; k++)
            crc = crc16_update(crc, (uint8_t)(u >> (8 * k)));
    }
    return crc;
}

// ---- output lines ---------------------------------------------------------------------------
static void out_begin(char type)
{
    g_out_len = 0;
    out_char('$');
    out_char(type);
    out_char(',');
    out_int(g_seq);
}

static void out_char(char c)
{
    if (g_out_len < MAX_LINE - 4) // room for "*CC\n"
        g_out[g_out_len++] = c;
}

static void out_int(int32_t v)
{
    char buf[12];
    ltoa(v, buf, 10);
    if (g_out_len > 1 && g_out[g_out_len - 1] != ',')
        out_char(',');
    for (char *p = buf; *p; p++)
        out_char(*p);
}

static void out_str_P(PGM_P s)
{
    out_char(',');
    for (char c; (c = pgm_read_byte(s)) != 0; s++)
        out_char(c);
}

static void out_hex(uint16_t v, uint8_t digits)
{
    out_char(',');
    while (digits--) {
        uint8_t d = (v >> (4 * digits)) & 0xF;
        out_char(d < 10 ? '0' + d : 'A' + d - 10);
    }
}

static void out_end()
{
    uint8_t crc = 0;
    for (uint8_t i = 1; i < g_out_len; i++)
        crc = crc8_update(crc, (uint8_t)g_out[i]);
    g_out[g_out_len++] = '*';
    g_out[g_out_len++] = "0123456789ABCDEF"[crc >> 4];
    g_out[g_out_len++] = "0123456789ABCDEF"[crc & 0xF];
    g_out[g_out_len++] = '\n';
    Serial.write((const uint8_t *)g_out, g_out_len); // blocks when the TX buffer is full
    g_seq++;
}

// ---- I2C ------------------------------------------------------------------------------------
static bool i2c_write(uint8_t addr, uint8_t reg, uint8_t v)
{
    Wire.beginTransmission(addr);
    Wire.write(reg);
    Wire.write(v);
    return Wire.endTransmission() == 0;
}

static bool i2c_read(uint8_t addr, uint8_t reg, uint8_t *buf, uint8_t n)
{
    Wire.beginTransmission(addr);
    Wire.write(reg);
    if (Wire.endTransmission(false) != 0) // repeated start
        return false;
    if (Wire.requestFrom(addr, n) != n)
        return false;
    for (uint8_t i = 0; i < n; i++)
        buf[i] = Wire.read();
    return true;
}

// The IMU: the first address that answers, recognised by its WHO_AM_I (0x75 on the MPU family,
// register 0x00 of bank 0 on the ICM-20948). A part that is neither is driven as an MPU-9150
// and its 0x75 reported, so the host can name what it found.
static bool imu_find()
{
    for (g_mpu = MPU_ADDR_AD0_LOW; g_mpu <= MPU_ADDR_AD0_HIGH; g_mpu++) {
        uint8_t who = 0;
        if (!i2c_read(g_mpu, MPU_WHO_AM_I, &who, 1))
            continue; // nobody at this address
        g_who = who;
        g_imu = (who == WHO_MPU9250 || who == WHO_MPU9255) ? IMU_MPU9250 : IMU_MPU9150;
        if (who == WHO_MPU9150 || g_imu == IMU_MPU9250)
            return true;
        i2c_write(g_mpu, ICM_REG_BANK_SEL, 0x00); // the bank may be any after an AVR reset
        if (i2c_read(g_mpu, ICM_WHO_AM_I, &who, 1) && who == WHO_ICM20948) {
            g_who = who;
            g_imu = IMU_ICM20948;
        }
        return true;
    }
    return false;
}

// Reset, wake (PLL clock), aux I2C master off, bypass on: the magnetometer appears at 0x0C.
static void imu_bypass()
{
    bool icm = g_imu == IMU_ICM20948;
    uint8_t pwr = icm ? ICM_PWR_MGMT_1 : MPU_PWR_MGMT_1;
    i2c_write(g_mpu, pwr, 0x80); // DEVICE_RESET (the ICM-20948 also returns to bank 0)
    delay(100);
    i2c_write(g_mpu, pwr, 0x01);
    i2c_write(g_mpu, icm ? ICM_USER_CTRL : MPU_USER_CTRL, 0x00); // I2C_MST_EN = 0
    delay(3);
    i2c_write(g_mpu, icm ? ICM_INT_PIN_CFG : MPU_INT_PIN_CFG, 0x02); // BYPASS_EN
}

// WIA (0x48 on every AKM part) and the register after it: the AK09916's WIA2 (0x09), INFO on
// the others. The AK8975 and AK8963 share their WIA; the IMU tells them apart.
static void mag_find()
{
    uint8_t id[2];
    g_mag = MAG_NONE;
    if (!i2c_read(AK_ADDR, AK_WIA, id, 2))
        return;
    if (g_imu == IMU_ICM20948 || id[1] == AK09916_WIA2_VALUE) {
        g_mag = MAG_AK09916;
        g_wia = id[1];
    } else {
        g_mag = g_imu == IMU_MPU9250 ? MAG_AK8963 : MAG_AK8975;
        g_wia = id[0];
    }
}

// The mode register: AK8975 CNTL, AK8963 CNTL1 (with the output BIT), AK09916 CNTL2.
static bool mag_mode(uint8_t mode)
{
    if (g_mag == MAG_AK09916)
        return i2c_write(AK_ADDR, AK09916_CNTL2, mode);
    if (g_mag == MAG_AK8963 && AK8963_BITS == 16)
        mode |= AK8963_BIT_16;
    return i2c_write(AK_ADDR, AK_CNTL, mode);
}

// Soft reset where there is one, the fuse-ROM ASA where there is one (the AK09916 has none:
// 128 is a factor of 1), power-down; and the resolution: µT per count, rails, bits.
static void mag_setup()
{
    g_asa[0] = g_asa[1] = g_asa[2] = 128;
    if (g_mag == MAG_AK09916) {
        i2c_write(AK_ADDR, AK09916_CNTL3, 0x01); // SRST
        delay(1);
        mag_mode(AK_POWER_DOWN);
        g_bits = 16, g_count_min = -32752, g_count_max = 32752, g_ut_per_count = 0.15f;
        return;
    }
    if (g_mag == MAG_AK8963) {
        i2c_write(AK_ADDR, AK8963_CNTL2, 0x01); // SRST
        delay(1);
        g_bits = AK8963_BITS;
        g_count_max = AK8963_BITS == 16 ? 32760 : 8190;
        g_count_min = -g_count_max;
        g_ut_per_count = AK8963_BITS == 16 ? 0.15f : 0.6f;
    } else {
        g_bits = 13, g_count_min = -4096, g_count_max = 4095, g_ut_per_count = 0.3f;
    }
    mag_mode(AK_POWER_DOWN);
    delay(1);
    mag_mode(AK_FUSE_ROM);
    delay(1);
    if (!i2c_read(AK_ADDR, AK_ASAX, g_asa, 3))
        g_asa[0] = g_asa[1] = g_asa[2] = 0;
    mag_mode(AK_POWER_DOWN);
    delay(1);
}

static bool mag_ready()
{
    uint8_t st1 = 0;
    return i2c_read(AK_ADDR, g_mag == MAG_AK09916 ? AK09916_ST1 : AK_ST1, &st1, 1) && (st1 & 0x01);
}

// A result nobody read leaves DRDY set; reading ST2 clears it.
static void mag_release()
{
    uint8_t st2;
    if (mag_ready())
        i2c_read(AK_ADDR, g_mag == MAG_AK09916 ? AK09916_ST2 : AK_ST2, &st2, 1);
}

// HXL..HZH and ST2 in one burst (the AK09916's TMPS between them): ST2 last, as the parts
// require, which ends the read.
static bool mag_read(int16_t h[3], uint8_t *st2)
{
    uint8_t b[8];
    uint8_t n = g_mag == MAG_AK09916 ? 8 : 7;
    if (!i2c_read(AK_ADDR, g_mag == MAG_AK09916 ? AK09916_HXL : AK_HXL, b, n))
        return false;
    for (uint8_t i = 0; i < 3; i++)
        h[i] = (int16_t)((uint16_t)b[2 * i] | ((uint16_t)b[2 * i + 1] << 8));
    *st2 = b[n - 1];
    return true;
}

// Find the IMU, open its bypass, find and set up the magnetometer. What was found goes in the
// hello; with no IMU or no magnetometer the identities read 00.
static void bring_up()
{
    g_who = g_wia = g_bits = 0;
    g_imu = IMU_NONE;
    g_mag = MAG_NONE;
    g_asa[0] = g_asa[1] = g_asa[2] = 0;
    g_count_min = -4096, g_count_max = 4095;
    g_ut_per_count = 0.3f;
    if (!imu_find()) {
        g_mpu = MPU_ADDR_AD0_LOW;
        return;
    }
    imu_bypass();
    mag_find();
    if (g_mag != MAG_NONE)
        mag_setup();
}

// ---- replies --------------------------------------------------------------------------------
static void send_hello()
{
    out_begin('H');
    out_int(PROTO_VERSION);
    out_str_P(PSTR(FW_VERSION));
    out_hex(g_who, 2);
    out_hex(g_wia, 2);
    for (uint8_t i = 0; i < 3; i++)
        out_int(g_asa[i]);
    out_int(g_rate_hz);
    out_int(g_bits); // a v1 trailing field: the output resolution (0 without a magnetometer)
    out_end();
}

static void send_ack(uint16_t tag, char cmd)
{
    out_begin('A');
    out_int(tag);
    out_char(',');
    out_char(cmd);
    // the caller may add result fields before out_end()
}

static void send_error_P(uint16_t tag, char cmd, PGM_P code)
{
    out_begin('E');
    out_int(tag);
    out_char(',');
    out_char(cmd);
    out_str_P(code);
    out_end();
}

static void send_record(uint16_t tag)
{
    out_begin('C');
    out_int(tag);
    if (g_rec_status == REC_OK)
        out_str_P(PSTR("OK"));
    else if (g_rec_status == REC_BLANK)
        out_str_P(PSTR("BLANK"));
    else
        out_str_P(PSTR("CORRUPT"));
    for (uint8_t i = 0; i < RECORD_FIELDS; i++)
        out_int(g_rec_status == REC_OK ? g_rec[i] : 0);
    out_hex(g_rec_status == REC_OK ? g_rec_crc : 0, 4);
    out_end();
}

// ---- the calibration record in EEPROM -------------------------------------------------------
static void load_record()
{
    uint8_t raw[EE_SIZE];
    bool blank = true;
    for (uint8_t i = 0; i < EE_SIZE; i++) {
        raw[i] = EEPROM.read(i);
        if (raw[i] != 0xFF)
            blank = false;
    }
    memset(g_rec, 0, sizeof g_rec);
    g_rec_crc = 0;
    if (blank) {
        g_rec_status = REC_BLANK;
        return;
    }
    int32_t v[RECORD_FIELDS];
    for (uint8_t i = 0; i < RECORD_FIELDS; i++) {
        const uint8_t *p = raw + 1 + 4 * i;
        v[i] = (int32_t)((uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
                         ((uint32_t)p[3] << 24));
    }
    uint16_t stored = (uint16_t)raw[EE_SIZE - 2] | ((uint16_t)raw[EE_SIZE - 1] << 8);
    if (raw[0] != EE_MAGIC || v[0] != 1 || record_crc(v) != stored) {
        g_rec_status = REC_CORRUPT;
        if (g_mode == 1)
            g_mode = 0; // never apply a record we cannot trust
        return;
    }
    memcpy(g_rec, v, sizeof g_rec);
    g_rec_crc = stored;
    g_rec_status = REC_OK;
}

static void store_record(const int32_t *v)
{
    uint16_t crc = record_crc(v);
    EEPROM.update(0, EE_MAGIC);
    for (uint8_t i = 0; i < RECORD_FIELDS; i++) {
        uint32_t u = (uint32_t)v[i];
        for (uint8_t k = 0; k < 4; k++)
            EEPROM.update(1 + 4 * i + k, (uint8_t)(u >> (8 * k)));
    }
    EEPROM.update(EE_SIZE - 2, (uint8_t)(crc & 0xFF));
    EEPROM.update(EE_SIZE - 1, (uint8_t)(crc >> 8));
    load_record(); // what is reported is what reads back
}

// ---- measurements ---------------------------------------------------------------------------
static float counts_to_ut(int16_t counts, uint8_t axis)
{
    return (float)counts * (g_ut_per_count / 256.0f) * (float)(g_asa[axis] + 128);
}

static void start_measurement(uint32_t now_us)
{
    // A result nobody read (a measurement in flight when the board reset, or one that finished
    // after a DRDY timeout) leaves DRDY set: it would be taken for the new one, read while the
    // next conversion runs (DERR), and every later read would be one measurement late.
    mag_release();
    g_trig_ms = millis();
    g_trig_us = now_us;
    if (!mag_mode(AK_SINGLE)) {
        out_begin('L');
        out_str_P(PSTR("I2C trigger failed"));
        out_end();
        return;
    }
    g_measuring = true;
    g_next_poll_us = now_us + DRDY_FIRST_POLL_US;
}

static void poll_measurement()
{
    uint32_t now = micros();
    if ((int32_t)(now - g_next_poll_us) < 0)
        return;
    if (mag_ready()) {
        finish_measurement();
        return;
    }
    if (now - g_trig_us > DRDY_TIMEOUT_US) {
        g_measuring = false;
        out_begin('L');
        out_str_P(PSTR("DRDY timeout"));
        out_end();
        return;
    }
    g_next_poll_us = now + DRDY_POLL_US;
}

static void finish_measurement()
{
    g_measuring = false;
    int16_t h[3];
    uint8_t st2;
    if (!mag_read(h, &st2)) {
        out_begin('L');
        out_str_P(PSTR("I2C read failed"));
        out_end();
        return;
    }
    uint8_t t[2] = {0, 0};
    i2c_read(g_mpu, g_imu == IMU_ICM20948 ? ICM_TEMP_OUT_H : MPU_TEMP_OUT_H, t, 2);
    int16_t temp = (int16_t)(((uint16_t)t[0] << 8) | t[1]);
    uint8_t a[6];
    int16_t accel[3];
    bool icm = g_imu == IMU_ICM20948;
    bool has_accel = g_imu != IMU_NONE && i2c_read(g_mpu, icm ? ICM_ACCEL_XOUT_H : MPU_ACCEL_XOUT_H, a, 6);
    for (uint8_t i = 0; i < 3; i++)
        accel[i] = (int16_t)(((uint16_t)a[2 * i] << 8) | a[2 * i + 1]);
    if (g_streaming)
        emit_sample(h, st2, temp, has_accel ? accel : 0);
    bool valid = !(st2 & (ST2_DERR | ST2_HOFL)) && (h[0] | h[1] | h[2]) != 0;
    for (uint8_t i = 0; i < 3; i++)
        if (h[i] <= g_count_min || h[i] >= g_count_max)
            valid = false;
    if (g_fit_kind && valid)
        fit_add(h);
}

// The magnetometer's self-test: power-down; the AK8975 and AK8963 then set ASTC.SELF and enter
// self-test mode (CNTL 0x08, datasheets MS1187-E-02 and MS1356-E-02), the AK09916 enters its
// self-test mode (CNTL2 0x10) with no ASTC; wait for DRDY, read HXL..ST2, ASTC.SELF off.
// Blocking (about 8 ms, 15 with a measurement in flight, which is finished and sent first: no
// sample is lost); streaming carries on with the next period. The reply carries the raw
// registers; the host applies ASA and judges them against the part's datasheet window.
static void self_test(uint16_t tag)
{
    while (g_measuring)
        poll_measurement(); // completes it (or gives up at the DRDY timeout)
    mag_release();
    bool astc = g_mag != MAG_AK09916;
    if (g_mag == MAG_NONE || !mag_mode(AK_POWER_DOWN) ||
        (astc && !i2c_write(AK_ADDR, AK_ASTC, ASTC_SELF))) {
        send_error_P(tag, 'T', PSTR("I2C"));
        return;
    }
    delayMicroseconds(100);
    bool ready = false;
    int16_t h[3];
    uint8_t st2 = 0;
    if (mag_mode(astc ? AK_SELF_TEST : AK09916_SELF_TEST)) {
        uint32_t t0 = micros();
        delayMicroseconds(DRDY_FIRST_POLL_US);
        while (micros() - t0 <= DRDY_TIMEOUT_US) {
            if (mag_ready()) {
                ready = mag_read(h, &st2);
                break;
            }
            delayMicroseconds(DRDY_POLL_US);
        }
    }
    if (astc)
        i2c_write(AK_ADDR, AK_ASTC, 0x00); // SELF must be off for normal measurements
    if (!ready) {
        mag_mode(AK_POWER_DOWN);
        send_error_P(tag, 'T', PSTR("I2C"));
        return;
    }
    send_ack(tag, 'T');
    for (uint8_t i = 0; i < 3; i++)
        out_int(h[i]);
    out_int(st2);
    out_end();
}

// S (or U) ms, h, st2, temp and, when the accelerometer answered, its three registers as
// read (raw counts at the reset range, +-2 g: 16384 per g) — trailing fields of protocol v1.
static void emit_sample(const int16_t h[3], uint8_t st2, int16_t temp, const int16_t *accel)
{
    if (g_mode == 1 && g_rec_status == REC_OK) {
        // h = W (m - o - t (T - tref)), all in nT; W in 1e-6, tref in 0.01 degC
        // the die temperature: MPU-9150 raw/340 + 36.53, MPU-9250 and ICM-20948 raw/333.87 + 21
        float temp_c100 = g_imu == IMU_MPU9150 || g_imu == IMU_NONE
                              ? (float)temp * (100.0f / 340.0f) + 3653.0f
                              : (float)temp * (100.0f / 333.87f) + 2100.0f;
        float dt_c = (temp_c100 - (float)g_rec[14]) * 0.01f;
        float v[3];
        for (uint8_t i = 0; i < 3; i++)
            v[i] = counts_to_ut(h[i], i) * 1000.0f - (float)g_rec[1 + i] -
                   (float)g_rec[11 + i] * dt_c;
        static const uint8_t widx[3][3] = {{5, 8, 9}, {8, 6, 10}, {9, 10, 7}};
        out_begin('U');
        out_int((int32_t)g_trig_ms);
        for (uint8_t r = 0; r < 3; r++) {
            float acc = 0.0f;
            for (uint8_t c = 0; c < 3; c++)
                acc += (float)g_rec[widx[r][c]] * 1e-6f * v[c];
            out_int((int32_t)lroundf(acc));
        }
    } else {
        out_begin('S');
        out_int((int32_t)g_trig_ms);
        for (uint8_t i = 0; i < 3; i++)
            out_int(h[i]);
    }
    out_int(st2);
    out_int(temp);
    for (uint8_t i = 0; accel && i < 3; i++)
        out_int(accel[i]);
    out_end();
}

// ---- standalone fit -------------------------------------------------------------------------
static void fit_add(const int16_t h[3])
{
    float p[3];
    for (uint8_t i = 0; i < 3; i++)
        p[i] = counts_to_ut(h[i], i);
    if (g_fit_count == 0)
        sphere_begin(&g_sums, g_fit_kind == 'F' ? p : 0); // centred on the first sample
    sphere_add(&g_sums, p[0], p[1], p[2]);
    if (++g_fit_count >= g_fit_target)
        fit_finish();
}

static void fit_finish()
{
    char kind = g_fit_kind;
    g_fit_kind = 0;
    float c[3], r;
    int32_t pivot = 0;
    int32_t o_nt[3] = {0, 0, 0}, r_nt = 0;
    int8_t ok = sphere_solve(&g_sums, c, &r, &pivot);
    if (ok == 0) {
        for (uint8_t i = 0; i < 3; i++)
            o_nt[i] = (int32_t)lroundf(c[i] * 1000.0f);
        r_nt = (int32_t)lroundf(r * 1000.0f);
    }
    out_begin('F');
    out_int(g_fit_tag);
    out_int(g_fit_count);
    for (uint8_t i = 0; i < 3; i++)
        out_int(o_nt[i]);
    out_int(r_nt);
    out_int(pivot);
    out_end();
    if (kind == 'F') {
        if (ok != 0) {
            send_error_P(g_fit_tag, 'F', PSTR("RANGE"));
            return;
        }
        int32_t v[RECORD_FIELDS] = {1, o_nt[0], o_nt[1], o_nt[2], r_nt,
                                    1000000L, 1000000L, 1000000L, 0, 0, 0,
                                    0, 0, 0, 0, 0, 0, 0};
        store_record(v);
        send_record(g_fit_tag);
    }
}

// ---- commands -------------------------------------------------------------------------------
static bool parse_int(const char *tok, int32_t *out)
{
    bool neg = false;
    if (*tok == '-' || *tok == '+')
        neg = (*tok++ == '-');
    if (!*tok)
        return false;
    int64_t v = 0;
    uint8_t digits = 0;
    for (; *tok; tok++) {
        if (*tok < '0' || *tok > '9' || ++digits > 10)
            return false;
        v = v * 10 + (*tok - '0');
    }
    if (neg)
        v = -v;
    if (v < -2147483648LL || v > 2147483647LL)
        return false;
    *out = (int32_t)v;
    return true;
}

// Upper-case hex of exactly `digits` digits; -1 when malformed.
static int32_t parse_hex(const char *tok, uint8_t digits)
{
    uint16_t v = 0;
    for (uint8_t i = 0; i < digits; i++) {
        char c = tok[i];
        uint8_t d;
        if (c >= '0' && c <= '9')
            d = c - '0';
        else if (c >= 'A' && c <= 'F')
            d = c - 'A' + 10;
        else
            return -1;
        v = (uint16_t)((v << 4) | d);
    }
    if (tok[digits] != 0)
        return -1;
    return (int32_t)v;
}

// `line` is everything between '$' and '\n' (the '\r' already dropped), NUL-terminated.
static void handle_line(char *line, uint8_t len)
{
    char *star = (char *)memrchr(line, '*', len);
    if (!star || (uint8_t)(line + len - star) != 3) {
        send_error_P(0, '?', PSTR("SYNTAX"));
        return;
    }
    int32_t want = parse_hex(star + 1, 2);
    uint8_t crc = 0;
    for (char *p = line; p < star; p++)
        crc = crc8_update(crc, (uint8_t)*p);
    if (want < 0) {
        send_error_P(0, '?', PSTR("SYNTAX"));
        return;
    }
    if ((uint8_t)want != crc) {
        send_error_P(0, '?', PSTR("CRC"));
        return;
    }
    *star = 0;
    char *tok[2 + MAX_ARGS];
    uint8_t ntok = 0;
    for (char *p = line;;) {
        if (ntok == 2 + MAX_ARGS) {
            ntok++; // too many
            break;
        }
        tok[ntok++] = p;
        char *comma = strchr(p, ',');
        if (!comma)
            break;
        *comma = 0;
        p = comma + 1;
    }
    int32_t tag;
    if (ntok < 2 || tok[0][0] < 'A' || tok[0][0] > 'Z' || tok[0][1] != 0 ||
        !parse_int(tok[1], &tag) || tag < 1 || tag > 65535) {
        send_error_P(0, '?', PSTR("SYNTAX"));
        return;
    }
    char cmd = tok[0][0];
    if (ntok > 2 + MAX_ARGS) {
        send_error_P((uint16_t)tag, cmd, PSTR("SYNTAX"));
        return;
    }
    int32_t args[MAX_ARGS];
    uint8_t nargs = ntok - 2;
    const char *crc_tok = 0;
    for (uint8_t i = 0; i < nargs; i++) {
        if (cmd == 'W' && i == MAX_ARGS - 1) { // the record CRC is hex
            crc_tok = tok[2 + i];
            args[i] = 0;
            continue;
        }
        if (!parse_int(tok[2 + i], &args[i])) {
            send_error_P((uint16_t)tag, cmd, PSTR("SYNTAX"));
            return;
        }
    }
    handle_command(cmd, (uint16_t)tag, args, nargs, crc_tok);
}

static void handle_command(char cmd, uint16_t tag, const int32_t *args, uint8_t nargs,
                           const char *crc_tok)
{
    uint8_t want;
    switch (cmd) {
    case 'I': case 'G': case 'X': case 'K': case 'D': case 'Z': case 'T': want = 0; break;
    case 'R': case 'M': case 'F': case 'N': want = 1; break;
    case 'W': want = MAX_ARGS; break;
    default:
        send_error_P(tag, '?', PSTR("UNKNOWN"));
        return;
    }
    if (nargs != want) {
        send_error_P(tag, cmd, PSTR("SYNTAX"));
        return;
    }
    switch (cmd) {
    case 'I':
        send_ack(tag, cmd);
        out_end();
        send_hello();
        break;
    case 'G':
        g_streaming = true;
        send_ack(tag, cmd);
        out_end();
        break;
    case 'X':
        g_streaming = false;
        send_ack(tag, cmd);
        out_end();
        break;
    case 'R':
        if (args[0] < 1 || args[0] > 100) {
            send_error_P(tag, cmd, PSTR("RANGE"));
            break;
        }
        g_rate_hz = (uint8_t)args[0];
        send_ack(tag, cmd);
        out_int(g_rate_hz);
        out_end();
        break;
    case 'M':
        if (args[0] == 0 || (args[0] == 1 && g_rec_status == REC_OK)) {
            g_mode = (uint8_t)args[0];
            send_ack(tag, cmd);
            out_int(g_mode);
            out_end();
        } else {
            send_error_P(tag, cmd, PSTR("RANGE"));
        }
        break;
    case 'K':
        send_record(tag);
        break;
    case 'D': // discard the record: the EEPROM is blank again and nothing is applied
        for (uint8_t i = 0; i < EE_SIZE; i++)
            EEPROM.update(i, 0xFF);
        load_record();
        g_mode = 0;
        send_ack(tag, cmd);
        out_end();
        send_record(tag);
        break;
    case 'W': {
        int32_t crc = crc_tok ? parse_hex(crc_tok, 4) : -1;
        if (crc < 0) {
            send_error_P(tag, cmd, PSTR("SYNTAX"));
            break;
        }
        if ((uint16_t)crc != record_crc(args)) {
            send_error_P(tag, cmd, PSTR("RECCRC"));
            break;
        }
        if (args[0] != 1) {
            send_error_P(tag, cmd, PSTR("RANGE"));
            break;
        }
        store_record(args);
        send_ack(tag, cmd);
        out_end();
        send_record(tag);
        break;
    }
    case 'Z':
        send_ack(tag, cmd);
        out_end();
        soft_reset();
        break;
    case 'T':
        self_test(tag);
        break;
    case 'F':
    case 'N':
        if (args[0] < 50 || args[0] > 2000) {
            send_error_P(tag, cmd, PSTR("RANGE"));
            break;
        }
        if (g_fit_kind) {
            send_error_P(tag, cmd, PSTR("BUSY"));
            break;
        }
        g_fit_kind = cmd;
        g_fit_tag = tag;
        g_fit_target = (uint16_t)args[0];
        g_fit_count = 0;
        send_ack(tag, cmd);
        out_int(g_fit_target);
        out_end();
        break;
    }
}

static void poll_serial()
{
    while (Serial.available() > 0) {
        char c = (char)Serial.read();
        if (c == '$') { // a '$' always starts a new line
            g_in_active = true;
            g_in_long = false;
            g_in_len = 0;
        } else if (!g_in_active) {
            // noise between lines
        } else if (c == '\n') {
            g_in_active = false;
            if (g_in_long) {
                send_error_P(0, '?', PSTR("LONG"));
            } else {
                g_in[g_in_len] = 0;
                handle_line(g_in, g_in_len);
            }
        } else if (c == '\r') {
            // allowed before '\n'
        } else if (g_in_len < MAX_LINE - 2) { // "$" + payload + "\n" <= 120 bytes
            g_in[g_in_len++] = c;
        } else {
            g_in_long = true; // keep reading until '\n', store nothing
        }
    }
}

// ---- lifecycle ------------------------------------------------------------------------------
static void soft_reset()
{
    Serial.flush();
    g_seq = 0;
    g_rate_hz = 50;
    g_streaming = false;
    g_mode = 0;
    g_measuring = false;
    g_fit_kind = 0;
    g_in_active = false;
    bring_up();
    load_record();
    g_sched_us = micros();
    send_hello();
}

void setup()
{
    Serial.begin(115200);
    Wire.begin();
    Wire.setClock(400000);
    Wire.setWireTimeout(5000, true); // a stuck bus must not hang the board (AVR core >= 1.8.3)
    soft_reset();
}

// Sleep until the next interrupt (timer0 every 1.024 ms, a received byte, a sent byte). Saves
// power on the board, and lets the emulator skip the idle cycles instead of simulating them.
static void idle()
{
    set_sleep_mode(SLEEP_MODE_IDLE);
    cli();
    if (Serial.available() > 0) {
        sei();
        return;
    }
    sleep_enable();
    sei(); // the instruction after SEI runs before any interrupt: no lost wake-up
    sleep_cpu();
    sleep_disable();
}

void loop()
{
    poll_serial();
    uint32_t now = micros();
    if (g_measuring) {
        if ((int32_t)(now - g_next_poll_us) >= 0)
            poll_measurement();
        else
            idle();
        return;
    }
    if (!g_streaming && !g_fit_kind) {
        idle();
        return;
    }
    uint32_t period = 1000000UL / g_rate_hz;
    if ((int32_t)(now - g_sched_us) < 0) {
        idle();
        return;
    }
    g_sched_us += period;
    if ((int32_t)(now - g_sched_us) > (int32_t)period) // fell behind: do not burst to catch up
        g_sched_us = now + period;
    start_measurement(now);
}
