// For comparison only, not shipped: the sample clock by millis() polling, as the example sketch docs/live.md
// showed before the firmware existed. `make SKETCH=millis_poll` builds it; tests/firmware measures its
// sample clock beside the firmware's.
void setup() {
  Serial.begin(115200);
  Serial.println("#needlecue-wire/1 channels=fsr1,fsr2,fsr3 adc_bits=10 vref_v=5.0 rate_hz=30");
}

void loop() {
  static unsigned long next = 0;
  unsigned long now = millis();
  if ((long)(now - next) < 0) return;
  next = now + 33;
  Serial.print(now);
  Serial.print(',');
  Serial.print(analogRead(A0));
  Serial.print(',');
  Serial.print(analogRead(A1));
  Serial.print(',');
  Serial.println(analogRead(A2));
}
